"""Stage 4 (kernels/build/radix_tree.cl) against an oracle written here from the
definition of Karras's (2012) binary radix tree: top-down, each node over the
sorted keys [first, last] splits where its keys first differ at the highest
bit (equal keys told apart by their index), and is numbered by Karras's rule
(the root is 0, a left child takes its parent's split, a right child that
split + 1, and leaf j is n - 1 + j).  The device builds the same tree
bottom-up in one pass (Apetrei 2014), so the arrays must be equal; boxes must
be the unions of the triangles below, and SAH costs and collapse flags must
follow the SAH recurrence."""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hlbvh_cl.core import layout
from hlbvh_cl.build.pipeline import Geometry
from hlbvh_cl.device.runtime import runtime
from hlbvh_cl.build.radix_tree import RadixTree, RadixTreeMetrics, build_radix_tree


def _augmented_gap(keys: np.ndarray, i: int) -> tuple[int, int]:
    """How much keys i and i + 1 differ, as Karras orders it: the key bits
    first, then the index bits (a larger value differs at a higher bit)."""
    return int(keys[i]) ^ int(keys[i + 1]), i ^ (i + 1)


def karras_oracle(keys: np.ndarray) -> dict[str, np.ndarray]:
    n = len(keys)
    out = {name: np.full(count, -7, np.int32) for name, count in (
        ("left_child", n - 1), ("right_child", n - 1), ("parent", 2 * n - 1),
        ("range_first", n - 1), ("range_last", n - 1))}
    out["parent"][0] = -1  # the root: internal node 0, or the lone leaf 0 when n == 1
    stack = [(0, 0, n - 1)] if n > 1 else []
    while stack:
        node, first, last = stack.pop()
        # the highest differing bit of a range is where its first and last keys differ
        split = max(range(first, last), key=lambda i: _augmented_gap(keys, i))
        left = split if split > first else n - 1 + split
        right = split + 1 if split + 1 < last else n - 1 + split + 1
        out["left_child"][node], out["right_child"][node] = left, right
        out["range_first"][node], out["range_last"][node] = first, last
        out["parent"][left] = out["parent"][right] = node
        if split > first:
            stack.append((split, first, split))
        if split + 1 < last:
            stack.append((split + 1, split + 1, last))
    return out


def run_device(keys: np.ndarray, bits: int, vertices: np.ndarray, collapse: bool):
    """build_radix_tree over triangle j = vertices[3j:3j+3] with the given
    sorted keys; returns (tree arrays, boxes, sah_cost, height, collapsed)."""
    rt = runtime()
    n = len(keys)
    faces = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    geometry = Geometry.upload(rt, vertices, faces, np.zeros(1, np.int32))
    key_buf = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                        hostbuf=keys)
    ids = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                    hostbuf=np.arange(n, dtype=np.uint32))
    with rt.pool.build():
        tree, metrics = RadixTree.allocate(rt, n), RadixTreeMetrics.allocate(rt, n)
        triangles, refs = (rt.pool.take(n * dtype.itemsize)
                           for dtype in (layout.TRIANGLE, layout.TRIANGLE_REF))
        vertex_ids = rt.pool.take(n * 12)
        build_radix_tree(rt, key_buf, bits, geometry.vertices, geometry.faces, ids,
                         geometry.mesh_first_face, 1, tree, metrics, triangles, refs, vertex_ids,
                         collapse_leaves=collapse)
        arrays = tree.read(rt.queue)
        boxes = np.empty(2 * n - 1, layout.AABB)
        cost = np.empty(2 * n - 1, np.float32)
        height = np.empty(2 * n - 1, np.int32)
        collapsed = np.empty(max(1, n - 1), np.int32)
        for host, device in ((boxes, metrics.boxes), (cost, metrics.sah_cost),
                             (height, metrics.height), (collapsed, metrics.collapsed)):
            cl.enqueue_copy(rt.queue, host, device)
        rt.queue.finish()
    return arrays, boxes, cost, height, collapsed[:n - 1]


def random_case(rng, n: int, bits: int, distinct: int):
    """n sorted keys drawn from `distinct` values (so runs of equal keys), and
    n random triangles."""
    dtype = np.uint32 if bits == 30 else np.uint64
    values = rng.integers(0, 2**bits, size=distinct, dtype=np.uint64)
    keys = np.sort(rng.choice(values, size=n)).astype(dtype)
    vertices = rng.normal(size=(3 * n, 3)).astype(np.float32)
    return keys, vertices


def check_against_oracle(keys, vertices, bits, collapse):
    n = len(keys)
    arrays, boxes, cost, height, collapsed = run_device(keys, bits, vertices, collapse)
    expected = karras_oracle(keys)
    for name, want in expected.items():
        assert np.array_equal(arrays[name], want), name
    # boxes: the union of the triangles under each node
    tri = vertices.reshape(n, 3, 3)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    for node in range(n - 1):
        first, last = arrays["range_first"][node], arrays["range_last"][node]
        assert np.array_equal(boxes["lo"][node], lo[first:last + 1].min(axis=0))
        assert np.array_equal(boxes["hi"][node], hi[first:last + 1].max(axis=0))
    assert np.array_equal(boxes["lo"][n - 1:], lo) and np.array_equal(boxes["hi"][n - 1:], hi)
    # the SAH recurrence (float64 here, so to a relative tolerance) and its collapse rule
    d = (boxes["hi"] - boxes["lo"]).astype(np.float64)
    area = 2 * (d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0])
    for node in range(n - 1):
        left, right = arrays["left_child"][node], arrays["right_child"][node]
        count = arrays["range_last"][node] - arrays["range_first"][node] + 1
        interior = area[node] + cost[left] + cost[right]
        leaf = count * area[node]
        if collapsed[node]:
            assert collapse and count <= layout.MAX_LEAF_SIZE
            assert cost[node] == pytest.approx(leaf, rel=1e-5)
            assert height[node] == 0  # a leaf of the final tree
        else:
            assert cost[node] == pytest.approx(interior, rel=1e-5)
            assert height[node] == 1 + max(height[left], height[right])
    assert collapse or not collapsed.any()
    assert (height[n - 1:] == 0).all()
    return collapsed


@pytest.mark.parametrize("bits", [30, 63])
@pytest.mark.parametrize("n, distinct", [(2, 1), (3, 3), (17, 4), (500, 500), (2000, 37),
                                         (1000, 1)])
def test_tree_matches_karras_definition(bits, n, distinct):
    rng = np.random.default_rng(n * 1000 + distinct + bits)
    keys, vertices = random_case(rng, n, bits, distinct)
    collapsed = check_against_oracle(keys, vertices, bits, collapse=True)
    if n >= 17:
        assert collapsed.any()  # the collapse rule was exercised


def test_one_primitive_is_a_lone_root_leaf():
    rng = np.random.default_rng(5)
    keys, vertices = random_case(rng, 1, 30, 1)
    arrays, boxes, _, height, _ = run_device(keys, 30, vertices, collapse=True)
    assert arrays["parent"].tolist() == [-1] and height.tolist() == [0]
    assert np.array_equal(boxes["lo"][0], vertices.min(axis=0))
    assert np.array_equal(boxes["hi"][0], vertices.max(axis=0))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(2, 300), distinct=st.integers(1, 300), seed=st.integers(0, 2**32 - 1),
       bits=st.sampled_from([30, 63]), collapse=st.booleans())
def test_property_random_keys(n, distinct, seed, bits, collapse):
    keys, vertices = random_case(np.random.default_rng(seed), n, bits, distinct)
    check_against_oracle(keys, vertices, bits, collapse)
