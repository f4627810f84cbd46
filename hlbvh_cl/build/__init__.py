"""Build: the stages that make a Tree from triangles, each a host module
paired by name with its kernel file in kernels/build/ (bounds, morton,
radix_tree, sah_top, flatten, widen, refit, dipoles), the pipeline that
runs them (pipeline), and two-level scenes of instances (instances).
Plain buffers pass between the stages (pbrt-v4's build, flatten, traverse).
It imports core, device and parallel."""
