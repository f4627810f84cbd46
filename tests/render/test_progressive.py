"""Progressive path tracing (Pipeline._progressive): rounds of one sample
over the whole image, to an spp target or a time budget, and Ctrl-C keeping
the rounds every pixel finished.  The oracle is the renderer itself on one
band: the same seed gives every pixel the same random streams however the
image is cut into bands and rounds."""
import numpy as np
import pyopencl as cl
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl.cli import main
from hlbvh_cl.io.exr import read_exr
from hlbvh_cl.render import renderer as renderer_module
from hlbvh_cl.render.integrators import path as path_module
from hlbvh_cl.render.camera import SPLAT_REACH
from hlbvh_cl import RenderInterrupted

WIDTH, HEIGHT = 48, 40


@pytest.fixture(scope="module")
def bunny_renderer(meshes, suite_device):
    scene = hlbvh_cl.Scene([meshes["bunny"]], device=suite_device)
    return hlbvh_cl.Renderer(scene, emitters=[{"type": "constant", "radiance": 1.0},
                                              {"type": "directional", "direction": [-1, -2, -1],
                                               "irradiance": 2.0}])


CAMERA = hlbvh_cl.Camera(eye=(0.0, 0.1, 0.3), target=(0.0, 0.1, 0.0))


def path(renderer, **options):
    return renderer.render(CAMERA, WIDTH, HEIGHT, shading="path", hdr=True, seed=3, **options)


@pytest.fixture
def bands_of_8_rows(monkeypatch):
    """Passes of 8 rows: the image becomes 5 bands."""
    monkeypatch.setattr(renderer_module, "PIXELS_PER_PASS", 8 * WIDTH)


def test_bands_and_rounds_do_not_change_the_image(bunny_renderer, monkeypatch):
    whole = path(bunny_renderer, spp=3)
    monkeypatch.setattr(renderer_module, "PIXELS_PER_PASS", 8 * WIDTH)
    banded = path(bunny_renderer, spp=3)
    assert bunny_renderer.stats["spp"] == 3
    assert whole.std() > 0.05  # a lit bunny, not a blank image
    np.testing.assert_allclose(banded, whole, rtol=1e-5, atol=1e-6)


def test_a_time_budget_stops_between_rounds(bunny_renderer):
    path(bunny_renderer, spp=1)  # kernels compiled before the clock runs
    image = path(bunny_renderer, time_budget=1e-6)
    assert bunny_renderer.stats["spp"] == 1  # at least one round, and no more past the budget
    np.testing.assert_allclose(image, path(bunny_renderer, spp=1), rtol=1e-6, atol=1e-7)
    path(bunny_renderer, time_budget=3600.0, spp=2)
    assert bunny_renderer.stats["spp"] == 2  # spp caps a budget


def test_bands_in_time_takes_the_first_bands_that_fit():
    bands = [renderer_module.Band(np.uint32(row), np.uint32(rows), 10, 10 * rows, None)
             for row, rows in ((0, 4), (4, 4), (8, 2))]  # 40 + 40 + 20 pixels
    fits = renderer_module.bands_in_time
    assert fits(bands, left=1.0, per_round=1.0) == 3  # a whole round fits
    assert fits(bands, left=0.95, per_round=1.0) == 2  # 0.4 + 0.4 fit, + 0.2 does not
    assert fits(bands, left=0.5, per_round=1.0) == 1
    assert fits(bands, left=0.39, per_round=1.0) == 0
    assert fits(bands, left=-1.0, per_round=1.0) == 0


def test_a_budget_cut_round_cuts_the_image_finer():
    bands = renderer_module.cut_bands(0, 720, 720, 1280)  # a 1280x720 frame, one pass
    finer = renderer_module.last_round_bands(bands, 720, 1280)
    tile = renderer_module.layout.TILE_ROWS
    assert len(finer) >= renderer_module.LAST_ROUND_BANDS - 1
    assert all(int(band.rows) % tile == 0 for band in finer[:-1])
    assert [int(band.first_row) for band in finer] == list(
        np.cumsum([0] + [int(band.rows) for band in finer[:-1]]))
    assert sum(int(band.rows) for band in finer) == 720
    passes = renderer_module.cut_bands(0, 720, 8, 1280)  # never coarser than the passes
    assert {int(band.rows) for band in renderer_module.last_round_bands(passes, 720, 1280)} \
        == {8}


def test_row_runs_group_rows_by_their_samples():
    taken = np.array([3, 3, 2, 2, 2, 3])
    assert renderer_module.row_runs(taken) == [(0, 2, 3), (2, 3, 2), (5, 1, 3)]
    assert renderer_module.row_runs(np.array([1, 1])) == [(0, 2, 1)]


@pytest.mark.parametrize("passes", ["one band", "bands of 8 rows"])
@pytest.mark.parametrize("rfilter", ["box", "gaussian"])
def test_a_budget_cut_round_adds_its_first_bands(bunny_renderer, monkeypatch, rfilter, passes):
    """When no whole round is left in the budget, the last round goes over
    the image cut finer (here in 5 bands of 8 rows) and takes the first
    bands that fit: their pixels are the mean of one sample more, also where
    the whole frame is one pass.  The gaussian film splats that round from
    its first rows only."""
    if passes == "bands of 8 rows":
        monkeypatch.setattr(renderer_module, "PIXELS_PER_PASS", 8 * WIDTH)
    one, two = path(bunny_renderer, spp=1, rfilter=rfilter), path(bunny_renderer, spp=2,
                                                                  rfilter=rfilter)
    monkeypatch.setattr(renderer_module, "LAST_ROUND_BANDS", HEIGHT // 8)
    monkeypatch.setattr(renderer_module, "bands_in_time",
                        lambda bands, left, per_round: min(len(bands) - 1, 2))
    splat = renderer_module.Film.splat_round

    def splat_then_poison(self, rt, width, height, stored):
        """NaN in the round's samples once splatted: the rows a cut round
        does not store again must never be read."""
        done = splat(self, rt, width, height, stored)
        round_buffer = self.splat["round"]
        cl.enqueue_fill_buffer(rt.queue, round_buffer, np.float32(np.nan), 0, round_buffer.size)
        return done
    monkeypatch.setattr(renderer_module.Film, "splat_round", splat_then_poison)
    cut = path(bunny_renderer, time_budget=3600.0, rfilter=rfilter)
    stats = bunny_renderer.stats
    assert stats["spp"] == 1 and stats["mean_spp"] == pytest.approx((16 * 2 + 24 * 1) / 40)
    assert stats["primary_rays"] == WIDTH * (16 * 2 + 24)
    reach = 0 if rfilter == "box" else SPLAT_REACH
    # rows 0..15 (bands 0 and 1) took the second sample; rows the filter
    # carries it to lie within reach of row 16
    np.testing.assert_allclose(cut[:16 - reach], two[:16 - reach], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(cut[16 + reach:], one[16 + reach:], rtol=1e-5, atol=1e-6)
    assert np.isfinite(cut).all() and not np.allclose(cut[:16], one[:16], rtol=1e-3)


def test_a_budget_cut_round_divides_the_aovs_by_each_rows_samples(bunny_renderer, monkeypatch):
    """The AOVs of the rows the cut round took are the means of two samples,
    the others' of one (read_aovs by row_runs)."""
    one, two = path(bunny_renderer, spp=1, aovs=True), path(bunny_renderer, spp=2, aovs=True)
    monkeypatch.setattr(renderer_module, "LAST_ROUND_BANDS", HEIGHT // 8)
    monkeypatch.setattr(renderer_module, "bands_in_time",
                        lambda bands, left, per_round: min(len(bands) - 1, 2))
    cut = path(bunny_renderer, time_budget=3600.0, aovs=True)
    for name in ("albedo", "normal", "depth"):
        ours, twice, once = getattr(cut, name), getattr(two, name), getattr(one, name)
        np.testing.assert_allclose(ours[:16], twice[:16], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(ours[16:], once[16:], rtol=1e-5, atol=1e-6)
    assert not np.allclose(one.depth[:16], two.depth[:16], rtol=1e-4)  # the rows differ


@pytest.mark.parametrize("time_budget, message", [(0, "time_budget"), (-1.0, "time_budget"),
                                                  (float("nan"), "time_budget")])
def test_bad_time_budgets_are_named(bunny_renderer, time_budget, message):
    with pytest.raises(ValueError, match=message):
        path(bunny_renderer, time_budget=time_budget)
    with pytest.raises(ValueError, match="shading='path'"):
        bunny_renderer.render(CAMERA, WIDTH, HEIGHT, time_budget=1.0)


def interrupt_at(monkeypatch, band_index: int, round_index: int, bands: int):
    """Ctrl-C as the film adds band ``band_index`` of round ``round_index``."""
    calls = []
    add = renderer_module.Film.add

    def add_or_stop(self, rt, band, width):
        if len(calls) == round_index * bands + band_index:
            raise KeyboardInterrupt
        calls.append(band)
        return add(self, rt, band, width)
    monkeypatch.setattr(renderer_module.Film, "add", add_or_stop)


def test_ctrl_c_keeps_the_rounds_every_pixel_finished(bunny_renderer, bands_of_8_rows,
                                                      monkeypatch):
    one, two = path(bunny_renderer, spp=1), path(bunny_renderer, spp=2)
    interrupt_at(monkeypatch, band_index=2, round_index=1, bands=5)
    with pytest.raises(RenderInterrupted) as stopped:
        path(bunny_renderer, spp=8)
    assert stopped.value.spp == 1 and bunny_renderer.stats["interrupted"]
    kept = stopped.value.image
    # bands 0 and 1 (rows 0..15) had their second sample; the rest one
    np.testing.assert_allclose(kept[:16], two[:16], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(kept[16:], one[16:], rtol=1e-5, atol=1e-6)


def test_ctrl_c_before_a_whole_image_is_a_plain_interrupt(bunny_renderer, bands_of_8_rows,
                                                          monkeypatch):
    interrupt_at(monkeypatch, band_index=3, round_index=0, bands=5)
    with pytest.raises(KeyboardInterrupt) as stopped:
        path(bunny_renderer, spp=4)
    assert not isinstance(stopped.value, RenderInterrupted)


def test_the_cli_renders_to_a_time_budget_and_keeps_an_interrupted_image(
        tmp_path, capsys, suite_device, monkeypatch):
    mesh = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=2).export(mesh)
    out = tmp_path / "ball.exr"
    argv = ["render", str(mesh), "--shading", "path", "--width", "32", "--height", "24",
            "--device", suite_device.id, "-o", str(out)]
    assert main(argv + ["--time", "600", "--spp", "3"]) == 0
    assert "3 spp" in capsys.readouterr().out  # the budget left the spp cap to stop it
    image = read_exr(out)
    assert image.shape == (24, 32, 3) and np.isfinite(image).all() and image.max() > 0
    out.unlink()
    # Ctrl-C in the third round: the CLI's 1-pixel warm-up render takes one
    # round first, whatever --spp says (it took all 16 once, and Ctrl-C then
    # stopped the warm-up and wrote nothing)
    interrupt_at(monkeypatch, band_index=0, round_index=1 + 2, bands=1)
    assert main(argv + ["--spp", "16"]) == 130
    assert "interrupted after 2 samples per pixel; wrote" in capsys.readouterr().err
    assert read_exr(out).shape == (24, 32, 3)


@pytest.mark.parametrize("shading, options", [("path", {}), ("ao", {"ao_samples": 4}),
                                              ("diffuse", {})])
def test_a_long_render_keeps_only_the_events_still_running(bunny_renderer, monkeypatch,
                                                          shading, options):
    """Each round's (a preview's each sample's) finished events are summed
    into the stage times and dropped: a render of many rounds held every
    event it had enqueued and summed them at its end (a CLI render of 60,000
    rounds grew to GBs, and Ctrl-C waited seconds for the sum).  The sums
    now take a few samples' events at a time, and every event summed lands
    in the stage times once.  The path integrator's events by depth
    (stats["depths"]) are folded the same way."""
    sizes, summed, held_by_depth = [], [], []
    event_ms, fold_events = renderer_module.event_ms, renderer_module.fold_events

    def summing(events):  # the render's last sum, of the events still held
        sizes.append(len(events))
        summed.append(event_ms(events))
        return summed[-1]

    def folding(pending, spent):  # the sums along the way
        held = {key: len(found) for key, found in pending.items()}
        before = {key: spent.get(key, 0.0) for key in pending}
        fold_events(pending, spent)
        sizes.extend(held[key] - len(pending[key]) for key in pending)  # per stage, as event_ms
        summed.append(sum(spent[key] - before[key] for key in pending))

    def folding_depths(pending, spent):
        held_by_depth.append(sum(len(found) for found in pending.values()))
        fold_events(pending, spent)
    monkeypatch.setattr(renderer_module, "event_ms", summing)
    monkeypatch.setattr(renderer_module, "fold_events", folding)
    monkeypatch.setattr(path_module, "fold_events", folding_depths)
    bunny_renderer.render(CAMERA, 4, 4, shading=shading, hdr=True, spp=300, **options)
    assert sum(sizes) > 300 * 2 and max(sizes) < 60, (sum(sizes), max(sizes))
    if shading == "path":  # a dozen launches or more a sample: thousands held if none were folded
        assert len(held_by_depth) > 300 and max(held_by_depth) < 300, max(held_by_depth)
    times = bunny_renderer.stats["times_ms"]
    assert times["closest"] > 0
    stages = sum(value for name, value in times.items() if name not in ("total", "setup", "wall"))
    assert stages == pytest.approx(sum(summed), rel=1e-9)


def test_depth_stats_split_the_bounce_stages_and_count_the_paths(bunny_renderer, bands_of_8_rows):
    """Renderer.stats["depths"] over 5 bands and 3 samples: every pixel's
    sample is shaded at depth 0, fewer paths at each depth after it, none
    past max_depth's last segment; each closest hit and shadow-ray launch
    lands in one depth's time (depth 0's closest: the camera rays'), the
    surface and resolve stages' too, beside the stage's other launches."""
    path(bunny_renderer, spp=3, max_depth=4)
    stats = bunny_renderer.stats
    depths, times = stats["depths"], stats["times_ms"]
    paths = depths["paths"]
    assert paths[0] == WIDTH * HEIGHT * 3 == stats["primary_rays"]
    # depth d shades the end of segment d + 1: max_depth 4, depths 0 to 3 at most
    assert 2 <= len(paths) <= 4 and all(a > b for a, b in zip(paths, paths[1:])), paths
    # the shadow rays the device counted: at most one a vertex, none at the
    # last (max_depth's last vertex samples no light); the renderer's
    # secondary rays are the bounces and those
    shadow_rays = depths["shadow_rays"]
    assert len(shadow_rays) == len(paths) and shadow_rays[0] > 0, shadow_rays
    assert all(0 <= s <= p for s, p in zip(shadow_rays, paths)), (shadow_rays, paths)
    if len(paths) == 4:
        assert shadow_rays[3] == 0
    assert stats["secondary_rays"] == sum(paths[1:]) + sum(shadow_rays)
    for stage in ("closest", "shade", "occluded", "resolve"):
        assert len(depths[stage]) == len(paths) and min(depths[stage]) >= 0, stage
    assert sum(depths["closest"]) == pytest.approx(times["closest"], rel=1e-9)
    assert sum(depths["occluded"]) == pytest.approx(times["occluded"], rel=1e-9)
    # shade also holds the counters' fills, resolve the film's sums
    assert 0 < sum(depths["shade"]) <= times["shade"]
    assert 0 < sum(depths["resolve"]) < times["resolve"]


def test_aovs_add_up_over_bands_and_rounds(bunny_renderer, monkeypatch):
    whole = path(bunny_renderer, spp=3, aovs=True)
    monkeypatch.setattr(renderer_module, "PIXELS_PER_PASS", 8 * WIDTH)
    banded = path(bunny_renderer, spp=3, aovs=True)
    assert whole.depth.max() > 0 and np.abs(whole.normal).max() > 0.5
    for name in ("image", "albedo", "normal", "depth"):
        np.testing.assert_allclose(getattr(banded, name), getattr(whole, name), rtol=1e-5,
                                   atol=1e-6, err_msg=name)
    interrupt_at(monkeypatch, band_index=2, round_index=1, bands=5)
    with pytest.raises(RenderInterrupted) as stopped:
        path(bunny_renderer, spp=8, aovs=True)
    assert stopped.value.image.depth.shape == (HEIGHT, WIDTH)  # a RenderResult, kept whole


def test_an_8_bit_path_render_is_srgb_of_the_linear_one(bunny_renderer):
    """Clipped to [0, 1], then IEC 61966-2-1's transfer function, per channel."""
    linear = path(bunny_renderer, spp=2).astype(np.float64)
    encoded = bunny_renderer.render(CAMERA, WIDTH, HEIGHT, shading="path", seed=3, spp=2)
    c = np.clip(linear, 0, 1)
    expected = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055) * 255
    assert encoded.dtype == np.uint8 and np.abs(encoded - expected).max() <= 0.5 + 1e-6
