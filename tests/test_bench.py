"""bench/build.py in --quick mode: the JSON it writes is complete and sane.

Never asserts speed: only that the figures exist, are finite and positive,
and agree with what the scenes must give (triangle counts from trimesh and
the scene file, binary-tree shape, SAH ratios of the reported costs).
"""
import json
import math
from pathlib import Path

import numpy as np
import pytest
from bench_support import json_numbers, load_bench
import trimesh

pytest.importorskip("matplotlib")
pytest.importorskip("mako")  # pyopencl's RadixSort, the sort peer

ROOT = Path(__file__).resolve().parent.parent




@pytest.fixture(scope="module")
def build_bench():
    return load_bench("build")


@pytest.fixture(scope="module")
def quick_run(build_bench, suite_device, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    returned = build_bench.main(["--quick", "--devices", suite_device.id, "--out", str(out),
                                 "--no-progress"])
    return returned, out




def _check_spread(times, where):
    assert set(times) == {"median", "min", "max"}, where
    assert 0 <= times["min"] <= times["median"] <= times["max"], (where, times)


def test_quick_json_is_complete_and_sane(build_bench, quick_run, suite_device):
    returned, out = quick_run
    written = json.loads((out / "build.json").read_text())
    assert written["quick"] is True and list(written["devices"]) == [suite_device.id]
    for where, number in json_numbers(written):
        assert math.isfinite(number), where

    config = build_bench.QUICK
    source = trimesh.load(ROOT / "scenes" / "meshes" / config.scaling_mesh, process=False)
    expected = {f"{Path(config.scaling_mesh).stem} part {n:,}": n for n in config.sizes}
    for name in config.meshes:
        expected[name] = len(trimesh.load(ROOT / "scenes" / "meshes" / name, process=False).faces)
    from hlbvh_cl.scenefile import load_scene_file
    expected[config.scene] = load_scene_file(ROOT / "scenes" / config.scene).triangle_count
    assert max(config.sizes) > len(source.faces)  # the series does exercise the split

    device = written["devices"][suite_device.id]
    assert device["errors"] == []
    cases = device["cases"]
    assert sorted((c["case"], c["builder"]) for c in cases) == sorted(
        (name, builder) for name in expected for builder in ("hlbvh", "lbvh"))
    for case in cases:
        where = f"{case['case']} {case['builder']}"
        assert case["triangles"] == expected[case["case"]], where
        assert case["sah_cost"] > 0, where
        # a binary tree: one interior node fewer than leaves, no deeper than needed
        assert case["nodes"] == case["leaves"] - 1, where
        assert 1 <= case["leaves"] <= case["triangles"], where
        assert case["depth"] >= math.ceil(math.log2(case["leaves"])), where
        assert case["first_build_ms"]["wall"] > 0, where
        for key in ("total", "wall"):
            _check_spread(case["times_ms"][key], where)
            assert case["times_ms"][key]["median"] > 0, where
        for stage in build_bench.STAGES:
            _check_spread(case["times_ms"][stage], where)
        refit = case["refit"]
        for key in ("upload", "refit", "wall"):
            _check_spread(refit["ms"][key], where)
        assert refit["ms"]["wall"]["median"] > 0 and refit["wall_vs_rebuild"] > 0, where
        # the last refit moves the vertices back: the boxes are the built ones again
        assert refit["sah_cost_after"] == pytest.approx(case["sah_cost"], rel=1e-3), where

    by_case = {}
    for case in cases:
        by_case.setdefault(case["case"], {})[case["builder"]] = case["sah_cost"]
    assert device["sah_ratios"] == pytest.approx(
        {name: costs["hlbvh"] / costs["lbvh"] for name, costs in by_case.items()})

    sort = device["sort"]
    assert sort["n"] == config.sort_n and set(sort["cases"]) == {"uint32 30-bit", "uint64 63-bit"}
    for name, result in sort["cases"].items():
        assert result["correct"] is True, name
        assert result["speedup_vs_numpy"] > 0, name
        _check_spread(result["ours"], name)
    assert sort["cases"]["uint32 30-bit"]["speedup_vs_pyopencl"] > 0

    assert (out / "build.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert returned["devices"].keys() == written["devices"].keys()


def test_broken_device_spec_is_listed_as_skipped(build_bench, suite_device):
    # a real device's name and a name that matches none: the bench runs on the
    # first, and lists the second and every device the first names that cannot
    # compile as skipped ("pocl": PyPI's PoCL on a CPU newer than its LLVM)
    import hlbvh_cl
    name = suite_device.id.split(":")[0]
    chosen, skipped = build_bench.pick_devices(f"{name},no-such-device")
    named = [d for d in hlbvh_cl.devices() if name in f"{d.id} {d.name} {d.platform}".lower()]
    assert len(chosen) == 1 and chosen[0] in named
    broken = [d.id for d in named if d.problem is not None]
    assert sorted(s["device"] for s in skipped) == sorted(broken + ["no-such-device"])


@pytest.mark.parametrize("triangles", [1, 700, 2_000, 7_999, 17_995])
def test_mesh_part_is_a_piece_of_the_split_surface(build_bench, triangles):
    from hlbvh_cl import Mesh
    source = Mesh.load(ROOT / "scenes" / "meshes" / "lucy_small.ply")  # 2,000 triangles
    part = build_bench.mesh_part(source, triangles)
    assert part.triangle_count == triangles
    assert np.unique(part.faces).size == part.vertex_count  # no unused vertices

    # Child i of the split lies in input face i // k**2 (split.py's order):
    # its centroid's barycentric coordinates there are in [0, 1].
    k = math.ceil(math.sqrt(triangles / source.triangle_count))
    child = np.asarray(part.vertices, np.float64)[part.faces]
    parent = np.asarray(source.vertices, np.float64)[source.faces[np.arange(triangles) // (k * k)]]
    a, e1, e2 = parent[:, 0], parent[:, 1] - parent[:, 0], parent[:, 2] - parent[:, 0]
    d = child.mean(axis=1) - a
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1, r2 = (d * e1).sum(1), (d * e2).sum(1)
    det = g11 * g22 - g12 * g12
    u, v = (g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det
    residual = np.linalg.norm(d - u[:, None] * e1 - v[:, None] * e2, axis=1)
    scale = np.sqrt(np.maximum(g11, g22))
    assert (u > -1e-4).all() and (v > -1e-4).all() and (u + v < 1 + 1e-4).all()
    assert (residual < 1e-4 * scale).all()

    # and the children of a whole input face cover it: same total area
    def areas(p):
        return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    whole = triangles // (k * k) * (k * k)
    assert areas(child[:whole]).sum() == pytest.approx(areas(parent[:whole]).sum() / (k * k),
                                                       rel=1e-5)
