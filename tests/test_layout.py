"""hlbvh_cl/layout.py mirrors kernels/hlbvh.h: sizes and offsets agree on the device."""
import numpy as np
import pyopencl as cl
import pytest

from hlbvh_cl import layout
from hlbvh_cl.device import devices, runtime
from hlbvh_cl.paths import kernel_dir

#: Every struct of layout.STRUCTS and each of its fields: (struct, None) is its size.
FIELDS = [(name, field) for name, dtype in layout.STRUCTS.items()
          for field in (None, *dtype.names)]

#: The probe kernel, written from FIELDS so that it covers every field the
#: numpy mirror names (OpenCL C has no offsetof: measure from a real, never
#: dereferenced, pointer).
PROBE = "#include \"hlbvh.h\"\n__kernel void struct_layout(__global int *out)\n{\n" + "".join(
    f"    out[{i}] = (int)sizeof({name});\n" if field is None else
    f"    out[{i}] = (int)((__global char *)&((__global {name} *)out)->{field}"
    f" - (__global char *)out);\n"
    for i, (name, field) in enumerate(FIELDS)) + "}\n"


@pytest.mark.parametrize("device", [d.id for d in devices() if d.problem is None])
def test_struct_layout_matches_device(device):
    rt = runtime(device)
    out = np.full(len(FIELDS), -1, np.int32)
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, out.nbytes)
    program = cl.Program(rt.context, PROBE).build(options=["-I", str(kernel_dir())])
    rt.run(program.struct_layout, 1, buf, local_size=1)
    cl.enqueue_copy(rt.queue, out, buf)
    expected = [layout.STRUCTS[s].itemsize if f is None else layout.STRUCTS[s].fields[f][1]
                for s, f in FIELDS]
    assert out.tolist() == expected


def test_constants_come_from_the_header():
    text = layout.HEADER.read_text()
    assert f"#define CLUSTER_BITS {layout.CLUSTER_BITS}" in text
    assert f"#define MAX_LEAF_SIZE {layout.MAX_LEAF_SIZE}" in text
    assert layout.EMPTY_CHILD == -1 and "#define EMPTY_CHILD (-1)" in text
    assert f"#define WIDE_ARITY {layout.WIDE_ARITY}" in text
