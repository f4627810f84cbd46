"""The salts the path integrator's host passes to its shading stage
(hlbvh_cl/render/random.py) against the kernels' own random_salt
(kernels/render/random.h), computed on the device: the two must agree bit
for bit, or a path render would draw other random numbers than its camera
and its tests expect."""
import numpy as np
import pyopencl as cl

from hlbvh_cl.core.paths import kernel_dir
from hlbvh_cl.device.runtime import quiet_build, runtime
from hlbvh_cl.render.random import salts8

SOURCE = """
#include "render/random.h"
__kernel void salts(const uint sample, const uint first, __global uint* out)
{
    uint k = get_global_id(0);
    out[k] = random_salt(sample, first + k);
}
"""


def test_host_salts_are_the_kernels(suite_device):
    rt = runtime(suite_device)
    program = quiet_build(cl.Program(rt.context, SOURCE), ["-I", str(kernel_dir())],
                          rt.device.cl_device)
    kernel = cl.Kernel(program, "salts")
    out = cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, 8 * 4)
    # the first bounce, a deep one, and a sample number past 2^31 (uint wrapping)
    for sample, first in ((0, 2), (7, 2 + 8 * 3), (2**31 + 5, 2 + 8 * 1023), (2**32 - 1, 0)):
        kernel(rt.queue, (8,), None, np.uint32(sample), np.uint32(first), out)
        got = np.empty(8, np.uint32)
        cl.enqueue_copy(rt.queue, got, out)
        want = np.array(salts8(sample, first).tolist(), np.uint32)
        np.testing.assert_array_equal(want, got, err_msg=f"sample {sample}, dimensions {first}..")
    assert len(set(got.tolist())) == 8  # eight different dimensions, eight salts
