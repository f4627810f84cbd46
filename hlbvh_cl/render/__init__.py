"""Render: cameras, lights, materials and emitters, settings, the film, and
the integrators that turn a built Scene into an image on the device
(kernels/render/; docs/rendering.md).  It
imports core, device, query and the Scene (through its borrow() seam)."""
