"""Rendering a Scene: the pipeline every integrator runs in.

Every per-pixel step runs on the device, in passes over whole rows (bands)
of at most PIXELS_PER_PASS pixels, and the host reads back one image
(8-bit, or float32 with hdr).
Per sample of each band:

    render/camera.cl   primary_rays       one Ray per pixel (camera.py)
    query/rays.cl      intersect_closest  -> Hit
    the integrator     its stages         adding to the film's sums
                                          (integrators/: direct.py's shading,
                                          shadow and AO rays; path.py's bounces)

and once a band's samples are summed, the film encodes it (film.py).  The
camera's convention is camera.py's, the film's encoding film.py's, and the
shading modes' definitions their integrator's (integrators/direct.py).
"""
from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import inputs, layout
from ..device.runtime import Runtime, event_ms, fold_events
from ..query.rays import RayQuery
from ..scene import Scene
from .camera import Camera, enqueue_primary_rays
from .film import Film
from .integrators import SHADINGS, integrator_for
from .emitters import check_emitters
from .integrators.base import Band, Look, Step
from .light import Light, check_light
from .materials import instance_material_table, material_table
from .settings import AO_SAMPLES, MAX_SPP, RR_DEPTH, RenderSettings, check_colors, default_colors

#: Pixels per pass at most (whole rows): a 1280 x 720 frame in one pass
#: (buffers of 133 bytes a pixel for the previews and about 210 for the
#: path integrator: up to 220 MB).  A pass costs the host about four
#: launches a bounce, and its last bounces keep few paths alive, which
#: leaves a GPU idle: there, 128K-pixel passes made a path-traced render
#: several times slower.  Both CPU runtimes were faster with 1M than with
#: 128K too, the reference scene's preview included (which had once
#: measured the other way).
PIXELS_PER_PASS = 1 << 20

#: The stages of a render's stats, in order.
STAGES = ("camera", "closest", "shade", "occluded", "resolve", "encode")


def check_settings(camera, width, height, shading="diffuse", shadows=True, spp=1,
                   ao_samples=AO_SAMPLES, ao_distance=None, max_depth=-1,
                   rr_depth=RR_DEPTH, seed=0, rfilter="box") -> RenderSettings:
    """Renderer.render's arguments, checked (shading: one of SHADINGS)."""
    return RenderSettings.check(camera, width, height, shading, shadows, spp, ao_samples,
                                ao_distance, SHADINGS, max_depth, rr_depth, seed, rfilter)


@dataclass(frozen=True)
class RenderResult:
    """Renderer.render(..., aovs=True): the image, and beside it the first
    hit's AOVs (Mitsuba 3's aov integrator), float32 means over each pixel's
    samples, zeros where the camera ray misses: ``albedo`` (H, W, 3), the
    material's reflectance (diffuse reflectance; a conductor's or
    dielectric's specular reflectance); ``normal`` (H, W, 3), the world
    shading normal; ``depth`` (H, W), the distance along the ray."""
    image: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray
    depth: np.ndarray


class Pipeline:
    """The render pipeline on one device: the camera stage, the closest-hit
    query, the integrators and the film, with buffers reused across renders.

    ``last_stats`` describes the last render: image size and options,
    spp (samples every pixel took) and mean_spp (their mean over the
    pixels: more where a time budget's last round covered the first rows),
    primary_rays and secondary_rays (rays launched past the primary ones:
    one per pixel and pass, pixels that need none getting an empty one; for
    path tracing, the bounce rays and shadow rays the device counted), and
    device times in milliseconds per stage (STAGES, and "total") plus
    "wall" (the whole call) and "setup" (part of wall: building or loading
    kernels, allocating buffers); for path tracing, "depths" splits the
    paths and the bounce stages' times by depth (integrators/path.py's
    Path.depth_stats).  PoCL finishes compiling a kernel at its
    first launch, and a tree's first query may prepare it for traversal:
    render once, small, to keep those out of a measurement.
    """

    #: Bytes per pixel of a pass of the pipeline's own buffers.
    PER_PIXEL = {"primary rays": layout.RAY.itemsize, "hits": layout.HIT.itemsize,
                 "hit instances": 4}

    def __init__(self, rt: Runtime, query: RayQuery | None = None):
        self.rt = rt
        # the default packet (1, 8 or 16 rays) is a pixel tile, half of one or one pixel
        self.query = query or RayQuery(rt)
        self.film = Film()
        self._integrators: dict[type, object] = {}
        self._pixels = 0
        self.overflow = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4)
        self._lock = threading.Lock()
        self.last_stats: dict = {}

    def chunk_rows(self, width: int, height: int, per_pixel: dict | None = None) -> int:
        """Image rows rendered per pass (PIXELS_PER_PASS, or fewer if one
        traversal launch holds fewer rays, or if the pass's buffers,
        ``per_pixel`` bytes a pixel by name, would not fit one allocation
        each or would take over a quarter of the device's memory, which the
        tree and the image share); whole bands of pixel tiles
        (layout.TILE_ROWS rows) when a pass holds one, so that only the
        image's last pass may end in a part band."""
        pixels = min(PIXELS_PER_PASS, self.query.max_rays_per_launch)
        if per_pixel:
            d = self.rt.device
            pixels = min(pixels, d.max_mem_alloc_size // max(1, max(per_pixel.values())),
                         d.global_mem_size // 4 // max(1, sum(per_pixel.values())))
            pixels = max(1, pixels)
        rows = max(1, min(height, pixels // width))
        if rows < height and rows >= layout.TILE_ROWS:
            rows -= rows % layout.TILE_ROWS
        return rows

    def render(self, tree, settings: RenderSettings, look: Look, progress: bool = False,
               hdr: bool = False, budget: float | None = None, aovs: bool = False):
        """The image, or with ``aovs`` (the path integrator's) a RenderResult."""
        with self._lock:  # the buffers are shared
            try:
                return self._render(tree, settings.in_frame(tree.scale), look, progress, hdr,
                                    budget, aovs)
            except BaseException:
                # Ctrl-C: the steps in flight (at most two) end before the
                # buffers serve another render.
                self.rt.queue.finish()
                raise

    def _reserve(self, integrator, pixels: int, image_pixels: int, hdr: bool,
                 aovs: bool = False, splat_groups: int = 0) -> None:
        """Buffers for passes of ``pixels`` and an image of ``image_pixels``
        (splatting ``splat_groups`` float4 per pixel), checked together
        against the device's limits first."""
        needed = self._sizes(integrator, pixels, image_pixels, hdr, aovs, splat_groups)
        self.rt.check_allocation(f"rendering {image_pixels:,} pixels, {pixels:,} at a time",
                                 needed)
        if pixels > self._pixels:
            context, rw = self.rt.context, cl.mem_flags.READ_WRITE
            self.primary = cl.Buffer(context, rw, pixels * layout.RAY.itemsize)
            self.hits = cl.Buffer(context, rw, pixels * layout.HIT.itemsize)
            self.instances = cl.Buffer(context, rw, pixels * 4)  # int32 per ray
            self._pixels = pixels
        self.film.reserve(self.rt, pixels, image_pixels, hdr)

    def _sizes(self, integrator, pixels: int, image_pixels: int, hdr: bool, aovs: bool,
               splat_groups: int) -> dict[str, int]:
        """Bytes of each buffer of a render (see _reserve)."""
        return {**{name: size * pixels for name, size in self.PER_PIXEL.items()},
                **self.film.sizes(pixels, image_pixels, hdr, splat_groups),
                **integrator.buffer_sizes(pixels),
                **(integrator.aov_sizes(pixels, 0 if splat_groups else image_pixels)
                   if aovs else {})}

    def _render(self, tree, settings: RenderSettings, look: Look, progress, hdr, budget,
                aovs):
        started = time.perf_counter()
        rt = self.rt
        width, height = settings.width, settings.height
        kind = integrator_for(settings.shading)
        integrator = self._integrators.setdefault(kind, kind())
        progressive = integrator.progressive
        splat_groups = (1 + integrator.AOV_GROUPS * aovs) if settings.splats() else 0
        rows = self.chunk_rows(width, height, self._sizes(integrator, 1, 0, hdr or progressive,
                                                          aovs, splat_groups))
        self._reserve(integrator, rows * width, width * height, hdr or progressive, aovs,
                      splat_groups)
        integrator.prepare(rt, settings, tree, look, rows * width)
        if aovs:  # a splatting film sums the AOVs itself: no AOV image
            integrator.prepare_aovs(rows * width, 0 if splat_groups else width * height)
        cl.enqueue_copy(rt.queue, self.overflow, np.zeros(1, np.int32))
        setup = time.perf_counter() - started

        passes = integrator.passes(settings)
        events = {name: [] for name in STAGES}
        bands = cut_bands(0, height, rows, width)
        steps: list[cl.Event] = []
        run = _Run(self, tree, settings, integrator, events, steps)
        if progressive:
            image, taken, mean_spp, interrupted = self._progressive(run, bands, hdr, progress,
                                                                    budget, aovs)
        else:
            image, taken, interrupted = self._band_by_band(run, bands, hdr, progress, passes)
            mean_spp = float(taken)
        overflow = np.zeros(1, np.int32)
        rt.wait([cl.enqueue_copy(rt.queue, overflow, self.overflow, is_blocking=False)])
        if overflow[0]:
            raise RuntimeError("ray traversal overflowed its stack: the tree is deeper than "
                               "its depth field says")
        times = {name: run.spent_ms[name] + event_ms(found) for name, found in events.items()}
        times["total"] = sum(times.values())
        times["setup"] = setup * 1e3
        times["wall"] = (time.perf_counter() - started) * 1e3
        pixels = round(width * height * mean_spp)  # camera rays
        secondary = pixels * passes
        if hasattr(integrator, "last_bounces"):  # paths: their bounces and shadow rays, counted
            secondary = sum(integrator.last_bounces) + sum(integrator.last_shadow_rays)
        self.last_stats = {"width": width, "height": height, "shading": settings.shading,
                           "shadows": settings.shadows, "spp": taken,
                           "mean_spp": mean_spp,
                           "primary_rays": pixels, "secondary_rays": secondary,
                           "times_ms": times, "interrupted": interrupted}
        if hasattr(integrator, "depth_stats"):  # paths: the same times, bounce by bounce
            self.last_stats["depths"] = integrator.depth_stats()
        if interrupted:
            raise RenderInterrupted(image, taken)
        return image

    def _band_by_band(self, run, bands, hdr, progress, passes):
        """Every sample of a band, then the next band (the preview modes:
        a band's buffers stay warm).  -> (image, spp, False)."""
        rt, settings, width = self.rt, run.settings, run.settings.width
        image = np.empty((settings.height, width, 3), np.float32 if hdr else np.uint8)
        bar = _progress_bar(progress, len(bands) * settings.spp * (1 + passes), "pass")
        with bar:
            run.bar = bar
            for band in bands:
                for sample in range(settings.spp):
                    run.sample(band, sample, sample)
                    run.fold_times()  # the samples still in flight stay (step_done: two)
                if hdr:
                    run.events["encode"].append(self.film.resolve(rt, band, width, settings.spp))
                else:
                    run.events["encode"].append(self.film.encode(
                        rt, band, width, settings.spp, run.integrator.radiance(settings)))
        rt.wait([self.film.read(rt, image)])
        return image, settings.spp, False

    def _progressive(self, run, bands, hdr, progress, budget, aovs):
        """Rounds of one sample per pixel over the whole image, each band's
        sums added to the image's, until spp rounds are done or, with a
        ``budget`` in seconds, the time left holds no more whole round: then
        a last round over the image cut finer (last_round_bands), as many of
        its first bands as fit (bands_in_time), so that the budget's tail is
        not left idle.  Each pixel is the mean of its own samples.  Ctrl-C
        stops it at once: the rounds every band finished make the image.
        -> (image, spp every pixel took, mean spp over the pixels,
        interrupted)."""
        rt, settings, width = self.rt, run.settings, run.settings.width
        film, integrator, splats = self.film, run.integrator, settings.splats()
        taken = np.zeros(settings.height, np.int64)  # samples added to each row's sums
        splatted = 0  # rounds splatted (splats)
        interrupted = False
        started = time.perf_counter()
        bar = _progress_bar(progress, None if budget is not None else settings.spp, "spp")
        with bar:
            try:
                if splats:
                    film.start_splatting(rt, settings.width * settings.height,
                                         1 + integrator.AOV_GROUPS * aovs)
                else:
                    film.clear(rt, settings.width * settings.height)
                this_round = bands  # a whole round, or the budget's last
                for sample in range(settings.spp):
                    stream, jitter = settings.stream(sample), settings.jitter()
                    for band in this_round:
                        run.sample(band, sample, 0)
                        if splats:
                            added = film.store_round(rt, band, width, film.accum, 1, 0, stream,
                                                     jitter)
                            if aovs:
                                added = film.store_round(rt, band, width, integrator.aov_sums,
                                                         integrator.AOV_GROUPS, 1, stream, jitter)
                        else:
                            added = film.add(rt, band, width)
                            if aovs:
                                run.events["encode"].append(added)
                                added = integrator.add_aovs(band, width)
                        run.events["encode"].append(added)
                        taken[int(band.first_row):int(band.first_row) + int(band.rows)] += 1
                    if splats:
                        stored = sum(int(band.rows) for band in this_round)
                        added = film.splat_round(rt, width, settings.height, stored)
                        run.events["encode"].append(added)
                        splatted += this_round is bands
                    rt.wait([added])
                    run.fold_times()
                    bar.update(1)
                    if this_round is not bands:
                        break  # the budget's last round, cut short
                    if budget is not None:
                        spent = time.perf_counter() - started
                        left, per_round = budget - spent, spent / (sample + 1)
                        if bands_in_time(bands, left, per_round) < len(bands):
                            finer = last_round_bands(bands, settings.height, width)
                            this_round = finer[:bands_in_time(finer, left, per_round)]
                            if not this_round:
                                break  # not one band fits
            except KeyboardInterrupt:
                rt.queue.finish()  # what was enqueued is in the sums
                if (splatted if splats else taken.min()) == 0:
                    raise  # not one whole image yet
                interrupted = True
        mean_spp = float(taken.mean())
        if splats:
            means = film.read_splatted(rt, settings.height, width)
            spp, image = splatted, means[:, :, 0, :3]
            if interrupted:
                mean_spp = float(splatted)  # a round cut short is not splatted
            if aovs:
                found = integrator.aovs_of_groups(means[:, :, 1:])
        else:
            image = np.empty((settings.height, width, 3), np.float32)
            rt.wait([film.read(rt, image)])
            # by float32 counts: numpy divides float32 by int64 in float64,
            # through a temporary of the whole image, and rounds back: the
            # same quotients (float32's division is correctly rounded, and a
            # double's rounded to float is too: 53 >= 2 * 24 + 2 bits)
            image /= taken.astype(np.float32)[:, None, None]
            spp = int(taken.min())
            if aovs:
                found = integrator.read_aovs(settings.height, width, row_runs(taken))
        image = np.ascontiguousarray(image) if hdr else srgb_encode(image)
        if aovs:
            image = RenderResult(image=image, **found)
        return image, spp, mean_spp, interrupted


def cut_bands(first_row: int, end_row: int, rows: int, width: int) -> list[Band]:
    """Rows [first_row, end_row) of an image ``width`` pixels wide as bands
    of ``rows`` rows (the last may be fewer), each with pixel_in_pass's 2D
    range (kernels/render: bands of TILE_ROWS rows)."""
    bands = []
    for row in range(first_row, end_row, rows):
        band_rows = min(rows, end_row - row)
        bands.append(Band(np.uint32(row), np.uint32(band_rows), width, band_rows * width,
                          (layout.TILE_ROWS * width, -(-band_rows // layout.TILE_ROWS))))
    return bands


#: A time budget's last round, which no whole round fits, goes over the
#: image in about this many bands (whole TILE_ROWS where the passes hold
#: them, never coarser than the passes), as many of the first as fit: a pass
#: holds 1M pixels, so a frame is often one band, and the budget's tail
#: would otherwise be left idle.  The time a band takes is estimated by its
#: share of pixels; its fixed cost (a few launches a bounce) comes on top.
LAST_ROUND_BANDS = 16


def last_round_bands(bands: list[Band], height: int, width: int) -> list[Band]:
    """The image's rows, from the top, as bands of about height /
    LAST_ROUND_BANDS rows: whole TILE_ROWS, but at most the passes' rows."""
    tile = layout.TILE_ROWS
    rows = -(-height // LAST_ROUND_BANDS)
    rows = min(max(int(band.rows) for band in bands), -(-rows // tile) * tile)
    return cut_bands(0, height, rows, width)


def row_runs(taken: np.ndarray) -> list[tuple[int, int, int]]:
    """(first row, rows, samples) for each run of rows that took the same
    number of samples."""
    edges = np.flatnonzero(np.diff(taken)) + 1
    starts = np.concatenate([[0], edges])
    ends = np.concatenate([edges, [len(taken)]])
    return [(int(a), int(b - a), int(taken[a])) for a, b in zip(starts, ends)]


def bands_in_time(bands, left: float, per_round: float) -> int:
    """How many of ``bands``, from the first, the next round takes when
    ``left`` seconds remain and a round has taken ``per_round`` (each band
    its share by pixels): all of them when a whole round fits, else the
    first bands that end within the time left (0: none)."""
    if per_round <= 0.0 or left >= per_round:
        return len(bands)
    total = sum(int(band.count) for band in bands)
    used, pixels = 0, 0
    for band in bands:
        pixels += int(band.count)
        if per_round * pixels / total > left:
            break
        used += 1
    return used


class _Run:
    """One render's fixed parts, and one sample of one band through them."""

    def __init__(self, pipeline, tree, settings, integrator, events, steps):
        self.pipeline, self.tree, self.settings = pipeline, tree, settings
        self.integrator, self.events, self.steps = integrator, events, steps
        self.pinhole = settings.camera.pinhole(settings.width, settings.height)
        self.bar = None
        self.spent_ms = {name: 0.0 for name in events}  # of the events fold_times dropped

    def fold_times(self) -> None:
        """Each stage's finished events summed into spent_ms and dropped:
        a render keeps no more than the events still running, so that one of
        60,000 rounds holds no more memory than one of a few, and Ctrl-C,
        after which the render sums the events left, is answered as soon."""
        fold_events(self.events, self.spent_ms)

    def step_done(self, event: cl.Event) -> None:
        """At most two steps (a pass's rays of one kind) in flight, so that
        Ctrl-C, which waits for them, is answered soon; a pass bar advances."""
        rt, steps = self.pipeline.rt, self.steps
        steps.append(event)
        if len(steps) > 2:
            rt.wait(steps[-3:-2])
            del steps[:-2]  # only the two in flight are kept
        if self.bar is not None:
            _advance(self.bar, rt, event)

    def sample(self, band: Band, sample: int, in_sum: int) -> None:
        """Sample ``sample`` of ``band``'s pixels, added to the film's sums
        (``in_sum``: how many the sums hold already; 0 starts them)."""
        p, settings, events = self.pipeline, self.settings, self.events
        stream = settings.stream(sample)
        events["camera"].append(enqueue_primary_rays(
            p.rt, settings.camera, self.pinhole, settings.width, settings.height, band, stream,
            settings.jitter(), p.primary))
        instances = p.instances if self.integrator.needs_instances else None
        events["closest"].append(p.query.enqueue_intersect(
            self.tree, p.primary, p.hits, band.count, p.overflow, instances=instances))
        self.integrator.shade(Step(p.rt, p.query, self.tree, band, in_sum, stream, p.primary,
                                   p.hits, p.film.accum, p.overflow, instances, events,
                                   self.step_done))


class RenderInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped a progressive render: ``image`` is the render of the
    ``spp`` samples per pixel every pixel had taken (as render would have
    returned it: with aovs, a RenderResult), for a caller to keep."""

    def __init__(self, image: np.ndarray, spp: int):
        super().__init__(f"render interrupted after {spp} samples per pixel")
        self.image, self.spp = image, spp


def srgb_encode(means: np.ndarray) -> np.ndarray:
    """float32 linear radiance -> 8-bit sRGB, the path tracer's tone map:
    each channel clipped to [0, 1] (NaN to 0), then the sRGB transfer
    function (IEC 61966-2-1: 12.92 c up to 0.0031308, else 1.055 c^(1/2.4) -
    0.055), rounded; as Mitsuba writes an 8-bit image of a linear film."""
    c = np.nan_to_num(np.clip(means.astype(np.float64), 0.0, 1.0), nan=0.0)
    encoded = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return np.round(encoded * 255.0).astype(np.uint8)


class Renderer:
    """Renders a Scene through a Camera.

    ``colors`` holds one RGB triple (0..1) per mesh (by default
    settings.PALETTE, cycled) and ``light`` a Light, which the preview modes
    read; ``materials`` (materials.py: one per mesh, Mitsuba 3's names) and
    ``emitters`` (emitters.py) are what the path integrator reads; in a
    scene with instances, ``instance_materials`` (one entry per instance:
    a material spec, or None for its mesh's) gives instances materials of
    their own, while emission stays its mesh's (an area emitter's mesh
    emits in every instance).  Each may be reassigned between renders,
    None giving the defaults again.
    ``stats`` describes the last render ({} before one):
    Pipeline.last_stats.  The first render compiles kernels: render once,
    small, to keep that out of a measurement.
    """

    def __init__(self, scene, colors=None, light: Light | None = None, materials=None,
                 emitters=None, instance_materials=None):
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a hlbvh_cl.Scene, got {type(scene).__name__}")
        self.scene = scene
        count = len(scene.meshes) + len(scene.spheres)  # geom_ids: meshes, then spheres
        self.colors = default_colors(count) if colors is None else colors
        self.light = Light() if light is None else light
        self.materials = materials
        self.emitters = emitters
        self.instance_materials = instance_materials
        self._pipeline: Pipeline | None = None

    @property
    def stats(self) -> dict:
        return self._pipeline.last_stats if self._pipeline is not None else {}

    def render(self, camera: Camera, width: int, height: int, shading: str = "diffuse",
               shadows: bool = True, spp: int | None = None, ao_samples: int = AO_SAMPLES,
               ao_distance: float | None = None, max_depth: int = -1,
               rr_depth: int = RR_DEPTH, seed: int = 0, rfilter: str = "box",
               hdr: bool = False, progress: bool = False,
               time_budget: float | None = None, aovs: bool = False):
        """A (height, width, 3) uint8 RGB image, or with ``hdr`` float32: the
        mean of each pixel's samples, linear.  shading is one of SHADINGS:
        "diffuse", "normals", "depth", "ao" (integrators/direct.py defines
        them), or "path" (integrators/path.py: path tracing, its paths at
        most ``max_depth`` segments long, -1 for no limit, with Russian
        roulette from ``rr_depth`` on).  spp samples per pixel, their random
        numbers fixed by ``seed`` (the same seed, the same image; seed > 0
        jitters even one sample per pixel) and spread over the pixel by
        ``rfilter``, "box" or "gaussian" (Mitsuba's, of standard deviation
        0.5 pixel); ao_samples AO
        rays per sample, reaching ao_distance (default 5% of the scene's
        diagonal).  progress shows a tqdm bar on stderr for renders longer
        than a second.

        "path" renders progressively, a sample per pixel over the whole
        image at a time: to ``spp`` samples, or with ``time_budget``
        (seconds) while whole rounds fit in it (at most ``spp`` if given;
        at least one round), then over the image's first rows that still
        fit: each pixel is the mean of its own samples.  stats["spp"] says
        how many samples every pixel took, stats["mean_spp"] their mean
        over the pixels.  Ctrl-C stops within a round's time and raises
        RenderInterrupted, whose ``image`` holds the samples every pixel
        had taken.  With ``aovs`` (shading "path" only) it returns a
        RenderResult: the image, and the first hit's albedo, shading normal
        and depth beside it, float32."""
        if time_budget is not None:
            if shading != "path":
                raise ValueError("time_budget is for shading='path' (the previews render "
                                 f"their spp in one go), not {shading!r}")
            time_budget = inputs.number("time_budget", time_budget, 0.0, low_open=True)
            spp = MAX_SPP if spp is None else spp
        settings = check_settings(camera, width, height, shading, shadows,
                                  1 if spp is None else spp, ao_samples,
                                  ao_distance, max_depth, rr_depth, seed, rfilter)
        if not isinstance(hdr, (bool, np.bool_)):
            raise TypeError(f"hdr must be True or False, got {type(hdr).__name__}")
        if not isinstance(aovs, (bool, np.bool_)):
            raise TypeError(f"aovs must be True or False, got {type(aovs).__name__}")
        if not isinstance(progress, (bool, np.bool_)):
            raise TypeError(f"progress must be True or False, got {type(progress).__name__}")
        if aovs and settings.shading != "path":
            raise ValueError(f"aovs=True needs shading='path' (the AOVs are the path "
                             f"integrator's), got shading={settings.shading!r}")
        with self.scene.borrow() as built:  # no rebuild or refit while the tree is read
            look = self.look()
            if self._pipeline is None:
                self._pipeline = Pipeline(built.runtime)  # its own queries and buffers
            return self._pipeline.render(built.tree, settings, look, progress=bool(progress),
                                         hdr=bool(hdr), budget=time_budget, aovs=bool(aovs))

    def look(self) -> Look:
        """colors, light, materials and emitters, checked, with the world
        triangles of the emitting meshes: what Pipeline.render shows."""
        count = len(self.scene.meshes) + len(self.scene.spheres)  # geom_ids: meshes, spheres
        colors = check_colors(default_colors(count) if self.colors is None else self.colors, count)
        light = check_light(Light() if self.light is None else self.light)
        emitters = check_emitters(self.emitters, count)
        triangles, normals = self._emissive(emitters)
        transforms = self.scene.transforms
        instance_maps = None if transforms is None else \
            np.linalg.inv(np.asarray(transforms, np.float64)[:, :, :3]).transpose(0, 2, 1)
        instance_meshes = self.scene.instance_meshes
        own, rows = instance_material_table(self.instance_materials, instance_meshes)
        return Look(colors, light, material_table(self.materials, colors), emitters,
                    triangles, normals, tuple(self.scene.meshes), instance_maps,
                    self._surface_area(transforms), own, rows, instance_meshes)

    def _surface_area(self, transforms) -> float:
        """The scene's world surface area: its meshes', each instance's scaled
        by |det A|^(2/3) of its map's linear part A (exact for a similarity)."""
        areas = np.array([m.area for m in self.scene.meshes], np.float64)
        if transforms is None:
            return float(areas.sum() + 4 * np.pi * (self.scene.spheres[:, 3] ** 2).sum())
        scales = np.abs(np.linalg.det(np.asarray(transforms, np.float64)[:, :, :3])) ** (2 / 3)
        return float((areas[self.scene.instance_meshes] * scales).sum())

    def _emissive(self, emitters) -> tuple[dict, dict]:
        """The world triangles of each emitting mesh (every instance's), and
        their corners' world shading normals (None: face normals); an
        emitting sphere's centre and radius (4,), and None.  A copy whose
        mask is 0, which no render ray can hit (they carry every mask bit),
        is left out: its light samples had lit the scene from a lamp that
        was not there, as only the light-sampled half of the estimate."""
        triangles, normals = {}, {}
        scene = self.scene
        seen = scene.masks != 0  # per instance, or per mesh without instances
        for mesh in emitters.area:
            if mesh >= len(scene.meshes):  # an analytic sphere: its centre and radius
                triangles[mesh], normals[mesh] = scene.spheres[mesh - len(scene.meshes)], None
                continue
            m = scene.meshes[mesh]
            corners = np.asarray(m.vertices, np.float64)[np.asarray(m.faces)]
            smooth = None if m.face_normals else \
                np.asarray(m.normals, np.float64)[np.asarray(m.faces)]
            if scene.transforms is None:
                kept = slice(None) if seen[mesh] else slice(0)
                triangles[mesh] = corners[kept]
                normals[mesh] = None if smooth is None else smooth[kept]
                continue
            maps = np.asarray(scene.transforms, np.float64)[(scene.instance_meshes == mesh)
                                                            & seen]
            triangles[mesh] = np.concatenate(
                [corners @ a[:, :3].T + a[:, 3] for a in maps]) if len(maps) \
                else np.zeros((0, 3, 3))
            normals[mesh] = None if smooth is None else np.concatenate(
                [smooth @ np.linalg.inv(a[:, :3]) for a in maps]) if len(maps) \
                else np.zeros((0, 3, 3))
        return triangles, normals


def _progress_bar(enabled: bool, total: int | None, unit: str):
    from tqdm import tqdm
    # Shown only once a render has taken a second (tqdm's delay).
    return tqdm(total=total, desc="rendering", unit=unit, file=sys.stderr, delay=1.0,
                leave=False, disable=not enabled)


def _advance(bar, rt: Runtime, event: cl.Event) -> None:
    if not bar.disable:  # waiting costs a sync per pass: only with a visible bar
        rt.wait([event])
        bar.update(1)
