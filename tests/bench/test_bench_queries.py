"""python -m bench.queries: its workloads against geometry worked out here,
each installed peer's answers against a float64 brute force, and its --quick
run's output, where the peers' answers must agree with ours.  Never asserts
speed."""
import json

import numpy as np
import pytest
from bench_support import ROOT, check_json
from oracle import chunks, moller_trumbore, prepare

pytest.importorskip("matplotlib")

from bench import peers, queries, report  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"


def point_distance(vertices, faces, points) -> np.ndarray:
    """Unsigned distance of each point to the nearest triangle, float64 brute force:
    the plane when the point projects inside the triangle, else the nearest edge."""
    a, b, c = (np.asarray(vertices, np.float64)[np.asarray(faces)[:, k]] for k in range(3))
    points = np.asarray(points, np.float64)
    best = np.empty(len(points))
    for start in range(0, len(points), 64):
        p = points[start:start + 64, None, :]
        n = np.cross(b - a, c - a)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        height = np.einsum("rfk,fk->rf", p - a, n)
        q = p - height[..., None] * n
        inside = np.ones(height.shape, bool)
        for s, e in ((a, b), (b, c), (c, a)):  # same side of all three edges as the normal
            inside &= np.einsum("rfk,fk->rf", np.cross(e - s, q - s), n) >= 0
        d = np.where(inside, np.abs(height), np.inf)
        for s, e in ((a, b), (b, c), (c, a)):
            t = np.clip(np.einsum("rfk,fk->rf", p - s, e - s) / ((e - s) ** 2).sum(1), 0, 1)
            d = np.minimum(d, np.linalg.norm(p - (s + t[..., None] * (e - s)), axis=2))
        best[start:start + 64] = d.min(axis=1)
    return best


def winding_number(vertices, faces, points) -> np.ndarray:
    """Generalised winding number, the sum of solid angles (Van Oosterom &
    Strackee 1983); 1 inside a closed outward-facing mesh, 0 outside."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    out = []
    for p in np.asarray(points, np.float64):
        a, b, c = (tri[:, k] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        numerator = np.einsum("fk,fk->f", a, np.cross(b, c))
        denominator = (la * lb * lc + np.einsum("fk,fk->f", a, b) * lc
                       + np.einsum("fk,fk->f", b, c) * la + np.einsum("fk,fk->f", c, a) * lb)
        out.append(np.arctan2(numerator, denominator).sum() / (2 * np.pi))
    return np.array(out)


def hit_counts(vertices, faces, origins, directions) -> np.ndarray:
    """Hits along each ray (t >= 0), tests/support/oracle.py's Moller-Trumbore in float64."""
    o, d, tmin, tmax, v0, e1, e2, _, valid = prepare(vertices, faces, origins, directions,
                                                     0.0, np.inf)
    counts = np.zeros(len(o), np.int64)
    for rays, tris in chunks(len(o), len(v0)):
        hit = moller_trumbore(o[rays], d[rays], v0[tris], e1[tris], e2[tris], valid[tris],
                              tmin[rays], tmax[rays])[3]
        counts[rays] += hit.sum(axis=1)
    return counts


@pytest.fixture(scope="module")
def bunny():
    case = queries.load_case("bunny_small.ply", None)
    config = queries.Config(("bunny_small.ply",), 150, 150, 50, 1, "bunny_small.ply", 150)
    return case, queries.workloads(case, config)


def test_workloads_fill_the_box_hug_the_surface_aim_at_the_centre_or_anywhere(bunny):
    case, works = bunny
    lo, hi = (np.asarray(x, np.float64) for x in case.box)
    centre, diagonal = (lo + hi) / 2, np.linalg.norm(hi - lo)
    uniform, near = works["closest_points"]
    grown = (hi - lo) * queries.QUICK.box_factor / 2
    assert (np.abs(uniform.points - centre) <= grown * (1 + 1e-6)).all()
    assert (np.abs(uniform.points - centre) > grown * 0.8).any(axis=0).all()  # it fills the box
    vertices, faces = case.geometry()
    d = point_distance(vertices, faces, near.points)
    assert d.max() <= queries.QUICK.near_fraction * diagonal * (1 + 1e-5)
    assert d.max() > queries.QUICK.near_fraction * diagonal * 0.5
    rays, wild = works["count_intersections"]
    for some in (rays, wild):
        assert (np.abs(some.origins - centre) <= (hi - lo) / 2 * (1 + 1e-6)).all()
        np.testing.assert_allclose(np.linalg.norm(some.directions, axis=1), 1, atol=1e-6)
    to_centre = centre - rays.origins
    np.testing.assert_allclose(np.cross(rays.directions, to_centre), 0, atol=1e-5 * diagonal)
    assert ((rays.directions * to_centre).sum(axis=1) > 0).all()
    # random directions: every octant, and a mean near 0 (|mean| of n random unit
    # vectors is about 1 / sqrt(n): here below 4 times that)
    octants = np.bincount((np.signbit(wild.directions) * [1, 2, 4]).sum(axis=1), minlength=8)
    assert octants.min() > 0
    assert np.linalg.norm(wild.directions.mean(axis=0)) < 4 / np.sqrt(len(wild))


@pytest.mark.parametrize("name", list(queries.PEERS))
def test_an_installed_peer_answers_as_the_brute_force(name, bunny):
    case, works = bunny
    available, missing = peers.load_peers([name], queries.PEERS)
    if missing:
        pytest.skip(f"{name} cannot run here: {missing[0].problem}")
    (peer,) = available
    vertices, faces = case.geometry()
    diagonal = np.linalg.norm(np.subtract(*case.box))
    peer.build(vertices, faces)
    try:
        for query in peer.queries:
            for work in works[query]:
                answer = peer.answer(query, peer.run(query, work), work)
                if query in queries.POINT_QUERIES:
                    expected = point_distance(vertices, faces, work.points)
                    np.testing.assert_allclose(np.abs(answer), expected, atol=1e-5 * diagonal)
                if query == "signed_distance":  # bunny_small is closed
                    inside = winding_number(vertices, faces, work.points) > 0.5
                    clear = expected > 1e-4 * diagonal
                    assert np.array_equal((answer < 0)[clear], inside[clear]), work.name
                if query in queries.RAY_QUERIES:
                    counts = answer if query == "count_intersections" else answer[0]
                    expected = hit_counts(vertices, faces, work.origins, work.directions)
                    assert 0 < expected.sum() and np.mean(counts != expected) <= 0.02, work.name
                if query == "intersect_all":
                    t = answer[1]
                    starts = np.cumsum(answer[0]) - answer[0]
                    assert (np.diff(t)[np.setdiff1d(np.arange(len(t) - 1), starts - 1)] >= 0).all()
    finally:
        peer.close()


def test_grouped_sorts_hits_by_ray_then_t():
    counts, t = queries.grouped([2, 0, 2, 0, 2], [5.0, 3.0, 1.0, 2.0, 4.0], 4)
    assert counts.tolist() == [2, 0, 3, 0] and t.tolist() == [2.0, 3.0, 1.0, 4.0, 5.0]


def test_ratios_name_the_fastest_peer_and_the_target():
    results = {"ours": {"mrate": {"median": 6.0}}, "open3d": {"mrate": {"median": 2.0}},
               "warp": {"mrate": {"median": 3.0}}}
    closest = queries.ratios("closest_points", results, ["ours"])["ours"]
    assert closest["peers"] == {"open3d": 3.0, "warp": 2.0}
    assert closest["target"] == {"factor": 3.0, "peer": "warp", "ratio": 2.0, "met": False}
    counted = queries.ratios("count_intersections", results, ["ours"])["ours"]["target"]
    assert counted == {"factor": 3.0, "peer": "open3d", "ratio": 3.0, "met": True}


def test_a_missing_peer_is_reported_not_raised(monkeypatch):
    class Absent(peers.Peer):
        name = distribution = "absent"
        modules = ("hlbvh_cl_no_such_module",)

    class Present(peers.Peer):  # numpy: there wherever the suite runs, unlike Open3D
        name = distribution = "numpy"
        modules = ("numpy",)

    monkeypatch.setitem(queries.PEERS, "absent", Absent)
    monkeypatch.setitem(queries.PEERS, "numpy", Present)
    available, missing = peers.load_peers(["absent", "numpy"], queries.PEERS)
    assert [p.name for p in missing] == ["absent"] and [p.name for p in available] == ["numpy"]
    assert "hlbvh_cl_no_such_module" in missing[0].problem
    with pytest.raises(ValueError, match="unknown peer 'embreex'"):
        peers.load_peers(["embreex"], queries.PEERS)


def test_the_results_section_replaces_its_copy_and_survives_the_suite_report(tmp_path):
    path = tmp_path / "RESULTS.md"
    path.write_text("# suite\n")
    for text in ("first", "second"):
        queries.write_section(path, f"<!-- begin queries -->\n{text}\n<!-- end queries -->\n")
    written = path.read_text()
    assert written.count("<!-- begin queries -->") == 1 and "second" in written
    assert "first" not in written and written.startswith("# suite\n")
    assert "second" in report.kept_sections(path)


def test_quick_run_writes_agreeing_answers_and_ratios(suite_device, tmp_path, capsys):
    committed = (ROOT / "bench" / "RESULTS.md").read_text()
    names = [n for n in queries.PEERS if not peers.load_peers([n], queries.PEERS)[1]]
    returned = queries.main(["--quick", "--devices", suite_device.id, "--peers", ",".join(names),
                             "--out", str(tmp_path), "--no-progress"])
    written = json.loads((tmp_path / "queries.json").read_text())
    check_json(written)
    assert (tmp_path / "queries.png").read_bytes()[:8] == PNG
    assert [c["name"] for c in written["cases"]] == list(queries.QUICK.cases)
    ours = suite_device.id
    for case in written["cases"]:
        assert case["errors"] == {} and len(case["runs"]) == 8  # 2 point sets x 2, 2 ray sets x 2
        for run in case["runs"]:
            results = run["results"]
            assert run["errors"] == {} and run["reference"] == ours
            able = {n for n in names if run["query"] in queries.PEERS[n].queries}
            assert set(results) == {ours} | able, run["query"]
            for name, r in results.items():
                assert r["mrate"]["median"] == pytest.approx(r["items"] / r["seconds"]["median"]
                                                             / 1e6)
                if name == ours:
                    continue
                gaps = r["vs_ours"]
                if run["query"] in queries.POINT_QUERIES:
                    assert gaps["max_distance_gap"] < 1e-5, (case["name"], run["query"], name)
                if "sign_differs" in gaps and case["name"].endswith(".ply"):  # closed: signs agree
                    assert gaps["sign_differs"] == 0, (run["workload"], name)
                if "count_differs" in gaps:
                    assert gaps["count_differs"] <= 0.01, (case["name"], run["query"], name)
                if "max_t_gap" in gaps:
                    assert gaps["max_t_gap"] < 1e-5
            target = run["ratios"][ours]["target"]
            if target["peer"] is not None:
                assert target["ratio"] == pytest.approx(
                    results[ours]["mrate"]["median"] / results[target["peer"]]["mrate"]["median"])
    memory = written["memory"]
    assert ours in memory["results"] and memory["errors"] == {}
    for r in memory["results"].values():
        assert r["output_bytes"] > 0 and r["peak_growth_bytes"] >= 0
    assert returned["cases"][0]["name"] == written["cases"][0]["name"]
    assert "M items/s" in capsys.readouterr().out
    assert (ROOT / "bench" / "RESULTS.md").read_text() == committed  # no --docs
