"""Device: finding OpenCL devices, choosing one, and running programs on it.

Discovery and the rules of a device spec (discovery, selection), the kernel
variants a device runs and the probe that proves them in a child process
(profile, probe, probe_child), and the runtime that owns a device's
context, queue, program cache and buffer pool (runtime, pool, hugepages).
It imports core only; probe_child, a program of its own run by the probe,
drives the whole package."""
