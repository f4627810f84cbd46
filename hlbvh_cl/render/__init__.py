"""Render: cameras, lights, settings, the film, and the integrators that
turn a built Scene into an image on the device (kernels/render/).  It
imports core, device, query and the Scene (through its borrow() seam)."""
