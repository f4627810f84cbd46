"""bench/trace.py: its ray generators against geometry worked out here, and
its --quick run's JSON against what the scenes must give.

Never asserts speed: only that the figures exist, are finite and positive,
that every participant finds the same hits (Embree, called directly here,
is the oracle), and that the derived figures (ratios, exponents) follow from
the reported ones.
"""
import json
import math
from pathlib import Path

import numpy as np
import pytest
from bench_support import json_numbers, load_bench
import trimesh

pytest.importorskip("matplotlib")
rtcs = pytest.importorskip("embreex.rtcore_scene")
from embreex.mesh_construction import TriangleMesh  # noqa: E402

import hlbvh_cl  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent




@pytest.fixture(scope="module")
def trace():
    return load_bench("trace")


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _angle(a, b):
    return math.acos(np.clip(np.dot(_unit(a), _unit(b)), -1, 1))


# ---------------------------------------------------------------- rays

def test_camera_rays_span_the_field_of_view(trace):
    camera = trace.Camera(eye=(1.0, 2.0, 3.0), target=(-2.0, 0.5, -1.0), up=(0.0, 1.0, 0.0),
                          fov_deg=50.0)
    width, height = 65, 49  # odd: a centre row and column exist
    origins, directions = trace.camera_rays(camera, width, height)
    assert origins.shape == directions.shape == (width * height, 3)
    assert origins.dtype == directions.dtype == np.float32
    np.testing.assert_allclose(origins, np.broadcast_to(camera.eye, origins.shape))
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1, atol=1e-6)

    grid = directions.reshape(height, width, 3).astype(np.float64)
    forward = _unit(np.subtract(camera.target, camera.eye))
    np.testing.assert_allclose(grid[height // 2, width // 2], forward, atol=1e-6)
    # pixel centres: the outer rows/columns are half a pixel inside the frustum
    half = math.tan(math.radians(camera.fov_deg) / 2)
    vertical = 2 * math.atan((1 - 1 / height) * half)
    horizontal = 2 * math.atan((1 - 1 / width) * half * width / height)
    assert _angle(grid[0, width // 2], grid[-1, width // 2]) == pytest.approx(vertical, rel=1e-5)
    assert _angle(grid[height // 2, 0], grid[height // 2, -1]) == pytest.approx(horizontal, rel=1e-5)
    # row 0 is the top (towards up), column 0 the left (away from forward x up)
    right = np.cross(forward, camera.up)
    assert np.dot(grid[0, width // 2], camera.up) > np.dot(grid[-1, width // 2], camera.up)
    assert np.dot(grid[height // 2, 0], right) < 0 < np.dot(grid[height // 2, -1], right)


@pytest.mark.parametrize("extent", [(1.0, 2.0, 0.5), (3.0, 0.2, 1.0), (1.0, 1.0, 1.0),
                                    (2.0, 0.0, 2.0)])
@pytest.mark.parametrize("aspect", [16 / 9, 4 / 3, 0.5])
def test_framed_camera_sees_the_whole_box(trace, extent, aspect):
    lo = np.array([-0.3, 1.0, 5.0])
    hi = lo + extent
    camera = trace.framed_camera(lo, hi, aspect)
    eye = np.array(camera.eye)
    forward = _unit(np.subtract(camera.target, eye))
    right = _unit(np.cross(forward, camera.up))
    up = np.cross(right, forward)
    half = math.tan(math.radians(camera.fov_deg) / 2)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) - eye
    depth = corners @ forward
    assert (depth > 0).all()
    across = np.abs(corners @ right) / depth / (half * aspect)
    along = np.abs(corners @ up) / depth / half
    assert max(across.max(), along.max()) <= 1.0  # every corner is in the picture
    assert max(across.max(), along.max()) >= 0.8  # and the box fills it


def test_incoherent_rays_start_on_a_sphere_and_cross_the_box(trace):
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([0.5, 3.0, 2.5])
    count = 5_000
    origins, directions = trace.incoherent_rays(lo, hi, count, seed=7)
    assert origins.shape == directions.shape == (count, 3)
    centre, radius = (lo + hi) / 2, trace.SPHERE_RADIUS_FACTOR * np.linalg.norm(hi - lo) / 2
    np.testing.assert_allclose(np.linalg.norm(origins - centre, axis=1), radius, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1, atol=1e-6)
    # slab test: each ray enters the box, ahead of its origin
    with np.errstate(divide="ignore"):
        inverse = 1 / directions.astype(np.float64)
    t0, t1 = (lo - origins) * inverse, (hi - origins) * inverse
    enter = np.minimum(t0, t1).max(axis=1)
    leave = np.maximum(t0, t1).min(axis=1)
    assert (enter <= leave * (1 + 1e-5)).all() and (leave > 0).all()
    # the origins cover the sphere: each octant around the centre gets its share
    octant = ((origins - centre) > 0) @ np.array([1, 2, 4])
    assert np.bincount(octant, minlength=8).min() > count / 8 * 0.8
    again = trace.incoherent_rays(lo, hi, count, seed=7)
    other = trace.incoherent_rays(lo, hi, count, seed=8)
    assert np.array_equal(again[1], directions) and not np.array_equal(other[1], directions)


def test_fit_exponent_recovers_a_power_law(trace):
    triangles = np.array([1e3, 1e4, 1e5, 3e6])
    assert trace.fit_exponent(triangles, 0.02 * triangles**0.37) == pytest.approx(0.37)
    assert trace.fit_exponent(triangles, np.full(4, 5.0)) == pytest.approx(0.0, abs=1e-12)
    assert trace.fit_exponent([1000], [1.0]) is None


# ---------------------------------------------------------------- peers

def test_a_missing_peer_is_reported_not_raised(trace, monkeypatch):
    class Absent(trace.Peer):
        name, distribution, label = "absent", "absent", "a peer that is not installed"
        modules = ("hlbvh_cl_no_such_module",)

    monkeypatch.setitem(trace.PEERS, "absent", Absent)
    available, missing = trace.load_peers(["absent", "embreex"])
    assert [p.name for p in available] == ["embreex"]
    assert [p.name for p in missing] == ["absent"]
    assert "hlbvh_cl_no_such_module" in missing[0].problem
    assert missing[0].describe()["available"] is False
    with pytest.raises(ValueError, match="unknown peer 'nope'"):
        trace.load_peers(["nope"])


class _FailsOnSecondQuery:
    """A peer that builds and warms up, then breaks in the timed rounds."""
    kind, name = "peer", "flaky"

    def __init__(self):
        self.calls, self.closed = 0, False

    def build(self, case):
        return 0.001

    def intersect(self, rays):
        self.calls += 1
        if self.calls > 1:
            raise RuntimeError("flaky peer gave up")
        return np.zeros(len(rays), bool)

    occluded = intersect

    def hits(self, result):
        return result

    def kernel_seconds(self):
        return None

    def close(self):
        self.closed = True


def test_a_failing_peer_is_reported_and_the_others_measured(trace, capsys, suite_device):
    case = trace.mesh_case("bunny_small.ply")
    config = trace.QUICK
    workloads = case.workloads(config)
    ours, flaky = trace.OurDevice(suite_device), _FailsOnSecondQuery()
    out = trace.bench_case(case, workloads, [ours, flaky], repeats=2)
    assert out["errors"] == {"flaky": "RuntimeError: flaky peer gave up"}
    assert flaky.closed and ours.scene is None
    assert [w["rays"] for w in out["workloads"]] == [len(r) for r in workloads]
    name = suite_device.id  # results are named by device id
    for workload in out["workloads"]:
        assert list(workload["results"]) == [name] and workload["reference"] == name
        assert workload["results"][name]["disagreement"] == {"intersect": 0.0, "occluded": 0.0}
        assert workload["ratios"] == {name: {}}
    assert "flaky peer gave up" in capsys.readouterr().err  # the traceback is shown


# ---------------------------------------------------------------- the quick run

@pytest.fixture(scope="module")
def device_ids(suite_device) -> list[str]:
    """The suite's device, and one more that works when there is one: hits
    must agree across devices."""
    others = (d.id for d in hlbvh_cl.devices()
              if d.id != suite_device.id and d.skipped_because is None)
    return [suite_device.id, *list(others)[:1]]


@pytest.fixture(scope="module")
def quick_run(trace, device_ids, tmp_path_factory):
    out = tmp_path_factory.mktemp("trace")
    returned = trace.main(["--quick", "--devices", ",".join(device_ids), "--out", str(out),
                           "--no-progress"])
    return returned, json.loads((out / "trace.json").read_text()), out




def _check_spread(values, where):
    assert set(values) == {"median", "min", "max"}, where
    assert 0 < values["min"] <= values["median"] <= values["max"], (where, values)


def _embree_hits(vertices, faces, origins, directions) -> int:
    """The oracle: one plain embreex call."""
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, vertices, faces)
    return int((scene.run(origins, directions) >= 0).sum())


def test_quick_json_is_complete_and_sane(trace, quick_run, device_ids):
    returned, written, out = quick_run
    assert written["quick"] is True
    assert returned["scenes"][0]["name"] == written["scenes"][0]["name"]
    for where, number in json_numbers(written):
        assert math.isfinite(number), where
    assert (out / "trace.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    config = trace.QUICK
    participants = written["participants"]
    devices = [n for n, p in participants.items() if p["kind"] == "device"]
    assert devices == device_ids
    assert set(trace.PEERS) <= set(participants)  # every peer: measured or reported missing
    for name in trace.PEERS:
        assert participants[name]["available"] or participants[name]["problem"], name
    assert participants["embreex"]["available"]
    running = [n for n, p in participants.items() if p["available"]]

    expected_scenes = {name: len(trimesh.load(ROOT / "scenes" / "meshes" / name, process=False).faces)
                       for name in config.meshes}
    from hlbvh_cl.scenefile import load_scene_file
    expected_scenes[config.scene] = load_scene_file(ROOT / "scenes" / config.scene).triangle_count
    assert [s["name"] for s in written["scenes"]] == list(expected_scenes)
    expected_rays = [w * h for w, h in config.resolutions] + [config.incoherent_rays]
    for scene in written["scenes"]:
        assert scene["errors"] == {}, scene["name"]
        assert scene["triangles"] == expected_scenes[scene["name"]]
        assert set(scene["build_s"]) == set(running)
        assert all(s > 0 for s in scene["build_s"].values())
        assert [w["rays"] for w in scene["workloads"]] == expected_rays
        for workload in scene["workloads"]:
            where = f"{scene['name']} {workload['name']}"
            results = workload["results"]
            assert set(results) == set(running), where
            assert workload["reference"] == "embreex"
            for name, r in results.items():
                for key in ("intersect_s", "occluded_s", "intersect_mrays", "occluded_mrays"):
                    _check_spread(r[key], f"{where} {name} {key}")
                assert r["intersect_mrays"]["median"] == pytest.approx(
                    workload["rays"] / r["intersect_s"]["median"] / 1e6)
                # with tmax = inf a ray is occluded exactly when it hits something
                assert r["occluded"] == r["hits"], f"{where} {name}"
            hits = {name: r["hits"] for name, r in results.items()}
            assert 0 < hits["embreex"] < workload["rays"], where  # rays both hit and miss
            for device in devices:
                assert hits[device] == hits["embreex"], (where, hits)
                assert results[device]["disagreement"] == {"intersect": 0.0, "occluded": 0.0}
                _check_spread(results[device]["intersect_kernel_s"], where)
                for peer in running:
                    if peer in devices:
                        continue
                    for q in ("intersect", "occluded"):
                        assert workload["ratios"][device][peer][q] == pytest.approx(
                            results[device][f"{q}_mrays"]["median"]
                            / results[peer][f"{q}_mrays"]["median"])


def test_quick_hits_match_a_direct_embree_call(trace, quick_run, suite_device):
    # the same rays, regenerated, traced by embreex in one plain call
    _, written, _ = quick_run
    config = trace.QUICK
    ours = suite_device.id
    mesh = hlbvh_cl.Mesh.load(ROOT / "scenes" / "meshes" / config.meshes[0])
    lo, hi = mesh.bounds()
    workloads = written["scenes"][0]["workloads"]
    for (width, height), workload in zip(config.resolutions, workloads):
        camera = trace.framed_camera(lo, hi, width / height)
        rays = trace.camera_rays(camera, width, height)
        assert workload["results"][ours]["hits"] == _embree_hits(mesh.vertices, mesh.faces, *rays)
    rays = trace.incoherent_rays(lo, hi, config.incoherent_rays, config.seed)
    assert workloads[-1]["results"][ours]["hits"] == _embree_hits(mesh.vertices, mesh.faces, *rays)


def test_quick_scaling_and_targets(trace, quick_run):
    _, written, _ = quick_run
    config = trace.QUICK
    scaling = written["scaling"]
    width, height = config.scaling_resolution
    faces = {name: len(trimesh.load(ROOT / "scenes" / "meshes" / name, process=False).faces)
             for name, _ in config.scaling}
    assert [p["triangles"] for p in scaling["points"]] == [faces[n] * k * k for n, k in config.scaling]
    devices = [n for n, p in written["participants"].items() if p["kind"] == "device"]
    assert set(scaling["alpha"]) == set(devices) | {"embreex"}
    for point in scaling["points"]:
        assert point["rays"] == width * height and point["errors"] == {}
        hits = {name: r["hits"] for name, r in point["results"].items()}
        assert 0 < hits["embreex"] < point["rays"], point["triangles"]
        assert all(h == hits["embreex"] for h in hits.values()), (point["triangles"], hits)
        for name, r in point["results"].items():
            _check_spread(r["intersect_s"], f"scaling {point['triangles']} {name}")
    # one surface, split finer: the same camera, and the same rays hit it
    counts = [p["results"]["embreex"]["hits"] for p in scaling["points"]]
    assert max(counts) - min(counts) <= 1e-3 * width * height + 1, counts
    assert set(scaling["alpha_min"]) == set(scaling["alpha"])
    for name in scaling["alpha"]:
        # least-squares slope in log-log, worked out here
        x = np.log([p["triangles"] for p in scaling["points"]])
        for key, which in (("alpha", "median"), ("alpha_min", "min")):
            y = np.log([p["results"][name]["intersect_s"][which] for p in scaling["points"]])
            slope = ((x - x.mean()) * (y - y.mean())).sum() / ((x - x.mean()) ** 2).sum()
            assert scaling[key][name] == pytest.approx(slope), (key, name)

    targets = written["targets"]
    assert len(targets) == 3 + len(devices)
    available = {n for n, p in written["participants"].items() if p["available"]}
    for target in targets:
        if target["value"] is None:  # only when the peer it compares with is missing
            assert target["met"] is None and "mitsuba" in target["what"]
            assert "mitsuba" not in available
            continue
        assert target["value"] > 0 or "exponent" in target["what"]
        assert target["met"] == (target["value"] >= target["target"] if target["comparison"] == ">="
                                 else target["value"] <= target["target"])
