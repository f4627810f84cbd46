"""python -m bench.trace: its rays against geometry worked out here, each
installed peer's hits against ours on the same rays, and its --quick run's
output.  Never asserts speed."""
import json
import math

import numpy as np
import pytest
from bench_support import ROOT, check_json
from chi2 import bin_directions, bin_shares, binned, p_value
from oracle import brute_force_intersect

import hlbvh_cl

pytest.importorskip("matplotlib")

from bench import peers, trace  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("extent", [(1.0, 2.0, 0.5), (3.0, 0.2, 1.0), (2.0, 0.0, 2.0)])
@pytest.mark.parametrize("aspect", [16 / 9, 0.5])
def test_framed_camera_sees_the_whole_box(extent, aspect):
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
    fill = max((np.abs(corners @ right) / depth / (half * aspect)).max(),
               (np.abs(corners @ up) / depth / half).max())
    assert 0.8 <= fill <= 1.0  # every corner is in the picture, and the box fills it


def test_incoherent_rays_start_on_a_sphere_and_cross_the_box():
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([0.5, 3.0, 2.5])
    rays = trace.incoherent_rays(lo, hi, 5_000, seed=7)
    centre, radius = (lo + hi) / 2, trace.SPHERE_RADIUS_FACTOR * np.linalg.norm(hi - lo) / 2
    np.testing.assert_allclose(np.linalg.norm(rays.origins - centre, axis=1), radius, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(rays.directions, axis=1), 1, atol=1e-6)
    with np.errstate(divide="ignore"):  # slab test: each ray enters the box ahead of its origin
        inverse = 1 / rays.directions.astype(np.float64)
    t0, t1 = (lo - rays.origins) * inverse, (hi - rays.origins) * inverse
    enter, leave = np.minimum(t0, t1).max(axis=1), np.maximum(t0, t1).min(axis=1)
    assert (enter <= leave * (1 + 1e-5)).all() and (leave > 0).all()
    again = trace.incoherent_rays(lo, hi, 5_000, seed=7)
    assert np.array_equal(again.directions, rays.directions)


def _plane_frame(normal):
    """A tangent frame about each unit normal by Gram-Schmidt against the
    axis it leans on least: the test's own, not the bench's."""
    axis = np.eye(3)[np.argmin(np.abs(normal), axis=1)]
    t = axis - (axis * normal).sum(axis=1, keepdims=True) * normal
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(normal, t)


def test_bounce_rays_leave_the_hit_cosine_distributed_and_skip_the_ground():
    # a tetrahedron (four facing ways, coordinates up to 40) and a flat ground
    tetra = hlbvh_cl.Mesh([[0, 0, 0], [40, 0, 0], [0, 20, 1], [3, 2, 10]],
                          [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    ground = hlbvh_cl.Mesh([[-9, -1, -9], [9, -1, -9], [9, -1, 9], [-9, -1, 9]],
                           [[0, 2, 1], [0, 3, 2]])
    rng = np.random.default_rng(5)
    count = 40_000
    geom = rng.choice([0, 0, 0, 1, -1], count)  # hits on both, and misses
    prim = np.where(geom == 0, rng.integers(0, 4, count), rng.integers(0, 2, count))
    u, v = rng.random((2, count)).astype(np.float32)
    u, v = np.where(u + v > 1, 1 - u, u), np.where(u + v > 1, 1 - v, v)
    incoming = rng.normal(size=(count, 3))
    incoming /= np.linalg.norm(incoming, axis=1, keepdims=True)
    camera = trace.Rays("camera", "primary", np.zeros((count, 3), np.float32),
                        incoming.astype(np.float32))
    rays = trace.bounce_rays([tetra, ground], camera, geom, prim, u, v, seed=11)
    assert rays.kind == "bounce" and len(rays) == (geom == 0).sum()  # the ground is left out
    assert rays.name == f"bounce {len(rays):,}"
    faces = tetra.faces[prim[geom == 0]]
    corners = tetra.vertices.astype(np.float64)[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal *= -np.sign((normal * incoming[geom == 0]).sum(axis=1))[:, None]  # faces the ray
    uu, vv = u[geom == 0, None], v[geom == 0, None]
    point = (1 - uu - vv) * corners[:, 0] + uu * corners[:, 1] + vv * corners[:, 2]
    lift = rays.origins - point
    offset = trace.BOUNCE_OFFSET * np.where((faces == 1).any(axis=1), 40, 20)  # largest coordinate
    np.testing.assert_allclose((lift * normal).sum(axis=1), offset, rtol=0.05)
    assert (np.linalg.norm(lift, axis=1) < 1.05 * offset).all()  # straight off the plane
    d = rays.directions.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-6)
    assert ((d * normal).sum(axis=1) > 0).all()  # in the hemisphere the ray came from
    # chi-squared against the cosine density cos(theta) / pi, in the test's own frames
    t, b = _plane_frame(normal)
    local = np.stack([(d * t).sum(axis=1), (d * b).sum(axis=1), (d * normal).sum(axis=1)], 1)
    cells, cell = bin_directions(10, 20, 4)
    expected = bin_shares(np.maximum(cells[:, 2], 0) / np.pi, cell, 10, 20, 4) * len(d)
    p, chi2, dof = p_value(binned(local, 10, 20), expected)
    assert p > 1e-3, (chi2, dof)
    again = trace.bounce_rays([tetra, ground], camera, geom, prim, u, v, seed=11)
    other = trace.bounce_rays([tetra, ground], camera, geom, prim, u, v, seed=12)
    assert np.array_equal(again.directions, rays.directions)
    assert np.array_equal(again.origins, rays.origins)
    assert not np.array_equal(other.directions, rays.directions)


def test_bounce_workload_starts_on_the_meshes_and_hits_as_brute_force(suite_device):
    case = trace.scene_file_case("bunny_small.toml", suite_device.id)  # a bunny on a ground
    _, primary, _, bounce = case.workloads([(20, 15), (40, 30)], 16, seed=4,
                                           bounce_device=suite_device.id)  # from the last
    assert (bounce.name, bounce.kind) == (f"bounce {len(bounce):,}", "bounce")
    vertices, faces = case.geometry()
    bunny = case.meshes[0].triangle_count
    assert case.meshes[1].triangle_count == 2 and np.ptp(case.meshes[1].vertices[:, 1]) == 0
    camera = brute_force_intersect(vertices, faces, primary.origins, primary.directions)
    on_bunny = (camera["prim"] >= 0) & (camera["prim"] < bunny)
    assert 0 < on_bunny.sum() < (camera["prim"] >= 0).sum()  # the ground is hit too, and left out
    assert len(bounce) == on_bunny.sum()
    # each starts just off the triangle the camera ray hit, on the camera's side
    source = camera["prim"][on_bunny]
    corners = vertices.astype(np.float64)[faces[source]]
    normal = camera["normal"][on_bunny]
    normal *= -np.sign((normal * primary.directions[on_bunny]).sum(axis=1))[:, None]
    height = ((bounce.origins - corners[:, 0]) * normal).sum(axis=1)
    np.testing.assert_allclose(height, trace.BOUNCE_OFFSET * np.abs(corners).max(axis=(1, 2)),
                               rtol=0.05)
    d = bounce.directions.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-6)
    assert ((d * normal).sum(axis=1) > 0).all()
    # our hits on them are the brute force's, and none falls back on its own triangle
    found = case.trace(bounce, suite_device.id)
    oracle = brute_force_intersect(vertices, faces, bounce.origins, bounce.directions)
    assert np.array_equal(found.hit, oracle["prim"] >= 0) and 0 < found.hit.sum() < len(bounce)
    flat = np.where(found.hit, np.cumsum([0, bunny])[np.maximum(found.geom_id, 0)]
                    + found.prim_id, -1)
    assert np.array_equal(flat, oracle["prim"])
    np.testing.assert_allclose(found.t[found.hit], oracle["t"][found.hit], rtol=1e-5)
    assert not (oracle["prim"] == source).any()


@pytest.fixture(scope="module")
def bunny_case(suite_device):
    case = trace.mesh_case("bunny_small.ply")
    return case, case.workloads([(48, 36)], 2048, seed=3, bounce_device=suite_device.id)


@pytest.mark.parametrize("name", list(peers.PEERS))
def test_an_installed_peer_finds_our_hits(name, bunny_case, suite_device):
    case, workloads = bunny_case
    available, missing = peers.load_peers([name])
    if missing:
        pytest.skip(f"{name} cannot run here: {missing[0].problem}")
    (peer,) = available
    ours = trace.OurDevice(suite_device)
    for participant in (ours, peer):
        assert trace.build_participant(participant, case) > 0
    try:
        for rays in workloads:
            hit = np.asarray(ours.hits(ours.intersect(rays)))
            assert 0 < hit.sum() < len(rays), rays.name  # rays both hit and miss
            assert np.array_equal(np.asarray(peer.hits(peer.intersect(rays)), bool), hit)
            assert np.array_equal(np.asarray(peer.occluded(rays), bool), ours.occluded(rays))
    finally:
        trace.close_all([ours, peer])


def test_a_missing_peer_is_reported_not_raised(monkeypatch):
    class Absent(peers.Peer):
        name = distribution = "absent"
        modules = ("hlbvh_cl_no_such_module",)

    monkeypatch.setitem(peers.PEERS, "absent", Absent)
    available, missing = peers.load_peers(["absent", "embreex"])
    assert [p.name for p in available] == ["embreex"] and [p.name for p in missing] == ["absent"]
    assert "hlbvh_cl_no_such_module" in missing[0].describe()["problem"]
    with pytest.raises(ValueError, match="unknown peer 'nope'"):
        peers.load_peers(["nope"])


class _FailsInTheTimedRounds:
    kind, name = "peer", "flaky"

    def __init__(self):
        self.calls, self.closed = 0, False

    def build(self, vertices, faces):
        return 0.001

    def intersect(self, rays):
        self.calls += 1
        if self.calls > 1:
            raise RuntimeError("flaky peer gave up")
        return np.zeros(len(rays), bool)

    occluded = intersect

    def hits(self, result):
        return result

    def close(self):
        self.closed = True


def test_a_failing_peer_is_reported_and_the_others_measured(bunny_case, suite_device):
    case, workloads = bunny_case
    ours, flaky = trace.OurDevice(suite_device), _FailsInTheTimedRounds()
    out = trace.bench_case(case, workloads, [ours, flaky], repeats=2)
    assert out["errors"] == {"flaky": "RuntimeError: flaky peer gave up"}
    assert flaky.closed and ours.scene is None
    for workload in out["workloads"]:
        assert list(workload["results"]) == [suite_device.id]
        assert workload["results"][suite_device.id]["disagreement"] == {"intersect": 0.0,
                                                                        "occluded": 0.0}


def test_quick_run_writes_agreeing_hits_ratios_and_fits(suite_device, tmp_path, capsys):
    committed = (ROOT / "docs" / "bench_trace.png").stat().st_mtime
    returned = trace.main(["--quick", "--devices", suite_device.id, "--peers", "embreex",
                           "--out", str(tmp_path), "--no-progress"])
    written = json.loads((tmp_path / "trace.json").read_text())
    check_json(written)
    assert (tmp_path / "trace.png").read_bytes()[:8] == PNG
    assert [s["name"] for s in written["scenes"]] == [s["name"] for s in returned["scenes"]] == [
        *trace.QUICK.meshes, trace.QUICK.scene]
    ours = suite_device.id
    for scene in written["scenes"]:
        assert scene["errors"] == {}
        for w in scene["workloads"]:
            results = w["results"]
            assert set(results) == {ours, "embreex"} and w["reference"] == "embreex"
            assert results[ours]["hits"] == results["embreex"]["hits"], w["name"]
            assert results[ours]["disagreement"] == {"intersect": 0.0, "occluded": 0.0}
            for q in ("intersect", "occluded"):
                assert w["ratios"][ours]["embreex"][q] == pytest.approx(
                    results[ours][f"{q}_mrays"]["median"] / results["embreex"][f"{q}_mrays"]["median"])
                assert results[ours][f"{q}_mrays"]["median"] == pytest.approx(
                    w["rays"] / results[ours][f"{q}_s"]["median"] / 1e6)
    scaling = written["scaling"]
    assert [p["triangles"] for p in scaling["points"]] == [
        trace.surface(n).triangle_count for n in trace.QUICK.scaling]
    x = np.log([p["triangles"] for p in scaling["points"]])
    for name, alpha in scaling["alpha"].items():  # least-squares slope, worked out here
        y = np.log([p["results"][name]["intersect_s"]["median"] for p in scaling["points"]])
        assert alpha == pytest.approx(((x - x.mean()) * (y - y.mean())).sum()
                                      / ((x - x.mean()) ** 2).sum())
    out = capsys.readouterr().out
    assert "closest hit, Mrays/s" in out and "time ~ triangles^alpha" in out
    assert (ROOT / "docs" / "bench_trace.png").stat().st_mtime == committed  # no --docs


def test_scene_option_traces_that_scene_file_alone(suite_device, tmp_path, capsys):
    returned = trace.main(["--quick", "--scene", "cornell_box.xml", "--devices", suite_device.id,
                           "--peers", "embreex", "--out", str(tmp_path), "--no-progress"])
    assert [s["name"] for s in returned["scenes"]] == ["cornell_box.xml"]
    assert returned["scaling"]["points"] == []
    (scene,) = returned["scenes"]
    assert scene["errors"] == {} and [w["kind"] for w in scene["workloads"]] == [
        "primary", "incoherent", "bounce"]
    for w in scene["workloads"]:
        assert w["results"][suite_device.id]["hits"] == w["results"]["embreex"]["hits"] > 0
        assert w["results"][suite_device.id]["disagreement"] == {"intersect": 0.0,
                                                                 "occluded": 0.0}
    assert (tmp_path / "trace.png").read_bytes()[:8] == PNG
    with pytest.raises(SystemExit, match="no scene file 'attic.xml'"):
        trace.main(["--quick", "--scene", "attic.xml", "--out", str(tmp_path)])


def test_compact_option_traces_each_device_compact_too(suite_device, tmp_path, capsys):
    returned = trace.main(["--quick", "--scene", "cornell_box.xml", "--devices", suite_device.id,
                           "--peers", "embreex", "--compact", "--out", str(tmp_path),
                           "--no-progress"])
    compact = f"{suite_device.id} compact"
    assert returned["participants"][compact]["compact"] is True
    (scene,) = returned["scenes"]
    assert scene["errors"] == {}
    trees = scene["trees"]
    assert trees[compact]["node_bytes"] == trees[suite_device.id]["node_bytes"]
    assert trees[compact]["triangle_bytes"] < trees[suite_device.id]["triangle_bytes"]
    for w in scene["workloads"]:
        results = w["results"]
        assert results[compact]["hits"] == results[suite_device.id]["hits"] > 0
        assert results[compact]["occluded"] == results[suite_device.id]["occluded"]
        assert results[compact]["disagreement"] == {"intersect": 0.0, "occluded": 0.0}
        assert set(w["ratios"]) == {suite_device.id, compact}
    assert compact in capsys.readouterr().out


class _Logged:
    """A participant that logs its name at each call."""

    def __init__(self, name, log):
        self.name, self.log = name, log

    def run(self):
        self.log.append(self.name)
        return len(self.log)


def test_each_timed_call_follows_an_untimed_call_of_its_own(monkeypatch):
    log, timed = [], []

    def stopwatch():  # the rounds' clock: notes which call it timed
        start = len(log)

        def elapsed():
            timed.append((start, log[start:]))
            return 1.0
        return elapsed
    monkeypatch.setattr(trace, "stopwatch", stopwatch)
    participants = [_Logged("a", log), _Logged("b", log), _Logged("c", log)]
    out = trace.time_round_robin(participants, lambda p: p.run(), 2, {})
    # the warm-up, then per round and participant an untimed call and a timed one
    assert log == ["a", "b", "c"] + ["a", "a", "b", "b", "c", "c"] * 2
    assert len(timed) == 6
    for start, calls in timed:
        assert calls == [log[start - 1]]  # one call timed, straight after its own
    assert {name: walls for name, (_, walls) in out.items()} == {
        "a": [1.0, 1.0], "b": [1.0, 1.0], "c": [1.0, 1.0]}
    assert out["c"][0] == len(log)  # the timed call's result is kept
