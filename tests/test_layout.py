"""hlbvh_cl/layout.py mirrors kernels/hlbvh.h: sizes and offsets agree on the device."""
import numpy as np
import pyopencl as cl
import pytest

from hlbvh_cl import layout
from hlbvh_cl.device import devices, runtime

FIELDS = [
    ("Aabb", None), ("Aabb", "hi"),
    ("FlatNode", None), ("FlatNode", "left_hi"), ("FlatNode", "right_lo"),
    ("FlatNode", "right_hi"), ("FlatNode", "left"), ("FlatNode", "right"),
    ("FlatNode", "left_count"), ("FlatNode", "right_count"),
    ("Triangle", None), ("Triangle", "v1"), ("Triangle", "v2"),
    ("TriangleRef", None), ("TriangleRef", "prim_id"),
    ("Ray", None), ("Ray", "tmin"), ("Ray", "direction"), ("Ray", "tmax"),
    ("Hit", None), ("Hit", "geom_id"), ("Hit", "prim_id"), ("Hit", "u"), ("Hit", "v"),
    ("Hit", "normal"),
    ("PinholeCamera", None), ("PinholeCamera", "forward"), ("PinholeCamera", "right"),
    ("PinholeCamera", "up"),
    ("ShadeParams", None), ("ShadeParams", "light_intensity"), ("ShadeParams", "ambient"),
    ("ShadeParams", "sky_up"), ("ShadeParams", "sky_horizon"), ("ShadeParams", "sky_zenith"),
    ("ShadeParams", "ray_offset"), ("ShadeParams", "depth_near"), ("ShadeParams", "depth_far"),
    ("ShadeParams", "ao_distance"), ("ShadeParams", "ao_weight"),
    ("WideNode", None), ("WideNode", "hi_x"), ("WideNode", "lo_y"), ("WideNode", "hi_y"),
    ("WideNode", "lo_z"), ("WideNode", "hi_z"), ("WideNode", "child"), ("WideNode", "count"),
]


@pytest.mark.parametrize("device", [d.id for d in devices() if d.problem is None])
def test_struct_layout_matches_device(device):
    rt = runtime(device)
    out = np.full(len(FIELDS), -1, np.int32)
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, out.nbytes)
    rt.run(rt.kernel("layout_probe.cl", "struct_layout"), 1, buf, local_size=1)
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
