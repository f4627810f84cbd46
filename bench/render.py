"""Render timings: scene files built and rendered (diffuse shading with
shadows), as the original report timed its renders.

Measuring scene files on a device (time_renders):

  1. load_scene reads each file and builds the BVH once: the reading is
     reported as ``load_s``, and that first build pays for compiling the
     build kernels (or loading them from the cache);
  2. a 1x1 render compiles the render kernels;
  3. one rebuild + render of each warms up (scratch buffers, caches);
  4. ``repeats`` rounds, each timing scene.rebuild() then scene.render() once
     per scene in turn, on the host ("wall", numpy image out).  Rounds rather
     than one scene's repeats after another's: on a shared machine a burst of
     load then falls on every scene alike, and ratios between rows (the
     fitted exponent alpha) do not depend on which row it hit.

"total" = rebuild + render of one repeat: the time to turn loaded triangles
into an image, without file reading or compilation.  Compilation is
estimated apart as (first build - median rebuild) + the 1x1 render.
"""
from __future__ import annotations

import hashlib
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # common.py, as build.py and trace.py do

import numpy as np  # noqa: E402
from common import cpu_seconds, stopwatch, summary  # noqa: E402

from hlbvh_cl import Camera  # noqa: E402
from hlbvh_cl.cli import load_scene  # noqa: E402

#: Shading of every timed render: what the report's renders did.
SHADING = {"shading": "diffuse", "shadows": True, "spp": 1}

# The original report's figures (build + render of one image, seconds).
#: Its table: per-mesh render time at REPORT_RESOLUTION, keyed by our scene file's stem.
REPORT_TIMES_S = {"bunny_small": 2.287, "armadillo_small": 2.576, "lucy_small": 2.597,
                  "bunny": 2.352, "armadillo": 2.822, "lucy": 3.009}
#: Its triangle counts, where known: only the table's first and last.
REPORT_TRIANGLES = {"bunny_small": 1_392, "lucy": 2_805_572}
REPORT_RESOLUTION = (1280, 720)
#: Its reference scene at 2048x1536 took "about 40 s"; the target is 10 s.
REPORT_REFERENCE_S = 40.0
TARGET_REFERENCE_S = 10.0
#: Targets for the reproduced table: each row this many times faster, and
#: time ~ triangles^alpha with alpha at most this.
TARGET_SPEEDUP = 20.0
TARGET_ALPHA = 0.15


def time_renders(paths, device_id: str, width: int, height: int, repeats: int,
                 builder: str = "hlbvh", bar=None) -> list[tuple[dict, np.ndarray] | Exception]:
    """Times ``repeats`` rounds of (rebuild + render) of each scene file in
    ``paths`` after a warm-up (module docstring): per file, (figures, the
    last image), or the exception that stopped that file (the others go
    on).  Times in seconds: "runs" lists each run's, "times_s" their
    {median, min, max}.  Every scene stays loaded until the end."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    timings: list = []
    for path in paths:
        try:
            timings.append(_SceneTiming(Path(path), device_id, width, height, builder))
        except Exception as error:  # one failure must not hide the other figures
            timings.append(error)
    for run in range(repeats + 1):  # run 0 warms up
        for k, timing in enumerate(timings):
            if isinstance(timing, Exception):
                continue
            if bar is not None:
                bar.set_postfix_str(f"{device_id} {timing.path.name} {width}x{height} "
                                    f"{'warm-up' if run == 0 else f'run {run}/{repeats}'}")
            try:
                timing.run(timed=run > 0)
            except Exception as error:
                timings[k] = error
    results = [t if isinstance(t, Exception) else (t.result(), t.image) for t in timings]
    del timings
    return results


class _SceneTiming:
    """One scene file loaded on a device, and its timed runs."""

    def __init__(self, path: Path, device_id: str, width: int, height: int, builder: str):
        self.path, self.width, self.height, self.builder = path, width, height, builder
        elapsed = stopwatch()
        self.scene, description, self.load_s = load_scene(path, device=device_id,
                                                          builder=builder)
        self.first_build_s = elapsed() - self.load_s
        c = description.camera
        self.camera = Camera(c.eye, c.target, c.up, c.fov_deg)
        warm = stopwatch()
        self.scene.render(self.camera, 1, 1, **SHADING)
        self.render_compile_s = warm()
        self.runs: list[dict] = []
        self.cpu_s = self.wall_s = 0.0
        self.image = None

    def run(self, timed: bool) -> None:
        cpu_before, whole = cpu_seconds(), stopwatch()
        self.scene.rebuild()
        build_s = whole()
        rendering = stopwatch()
        self.image = self.scene.render(self.camera, self.width, self.height, **SHADING)
        render_s = rendering()
        total_s = whole()
        if not timed:
            return
        # CPU time over wall time of the timed runs: how many cores the work
        # got (a CPU device's threads run in this process); well under the
        # device's compute units means another process took some, or the
        # work was too small
        self.cpu_s += cpu_seconds() - cpu_before
        self.wall_s += total_s
        self.runs.append({"build_s": build_s, "render_s": render_s, "total_s": total_s,
                          "build_device_s": self.scene.stats["times_ms"]["total"] * 1e-3,
                          "render_device_s": self.scene.render_stats["times_ms"]["total"] * 1e-3})

    def result(self) -> dict:
        rendered, stats, runs = self.scene.render_stats, self.scene.stats, self.runs
        times = {key: summary([r[key] for r in runs]) for key in runs[0]}
        rays = rendered["primary_rays"] + rendered["secondary_rays"]
        return {
            "scene": self.path.name, "device": self.scene.device.id, "builder": self.builder,
            "width": self.width, "height": self.height, **SHADING,
            "triangles": int(stats["triangles"]), "meshes": len(self.scene.meshes),
            "nodes": int(stats["nodes"]), "sah_cost": float(stats["sah_cost"]),
            "primary_rays": int(rendered["primary_rays"]),
            "secondary_rays": int(rendered["secondary_rays"]),
            "repeats": len(runs),
            "load_s": self.load_s,
            "compile_s": {"build": max(0.0, self.first_build_s - times["build_s"]["median"]),
                          "render": self.render_compile_s},
            "first_build_s": self.first_build_s,
            "times_s": times, "runs": runs, "cores_used": self.cpu_s / self.wall_s,
            "render_mrays": rays / times["render_s"]["median"] / 1e6,
            "image": image_summary(self.image),
        }


def image_summary(image: np.ndarray) -> dict:
    """What identifies an image in the JSON: its shape, mean and a digest."""
    return {"shape": list(image.shape), "mean": float(image.mean()),
            "sha256": hashlib.sha256(np.ascontiguousarray(image).tobytes()).hexdigest()[:16]}


def image_difference(a: np.ndarray, b: np.ndarray) -> dict:
    """How two renders of one scene differ: the fraction of pixels with any
    channel different, and the largest channel difference (0..255)."""
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} and {b.shape}")
    delta = np.abs(a.astype(np.int16) - b.astype(np.int16))
    return {"pixels_differing": float(np.mean(delta.max(axis=2) > 0)),
            "max_channel_difference": int(delta.max())}


def report_alpha() -> float:
    """The exponent of time ~ triangles^alpha through the report's first and
    last rows, the only two whose triangle counts it gives."""
    first, last = "bunny_small", "lucy"
    return math.log(REPORT_TIMES_S[last] / REPORT_TIMES_S[first]) / math.log(
        REPORT_TRIANGLES[last] / REPORT_TRIANGLES[first])
