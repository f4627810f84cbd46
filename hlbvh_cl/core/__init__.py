"""Core: the plain data and checks every layer shares.

The numpy mirror of the kernels' structs (layout), the tree the build makes
and the queries read (tree), the power-of-two frames of coordinates
(frame), the checks of every input (inputs), and where the kernels live
(paths).  It imports numpy and pyopencl only: nothing else of hlbvh_cl."""
