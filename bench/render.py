"""Render timings: scene files built and rendered (diffuse shading with
shadows), as the original report timed its renders (python -m bench's table).

Measuring scene files on a device (time_renders):
  1. hlbvh_cl.io.scenefile.load reads each file and builds it once: reading is
     ``load_s``, and that first build pays for compiling the build kernels;
  2. a 1x1 render compiles the render kernels;
  3. one rebuild + render of each warms up;
  4. ``repeats`` rounds, each timing Scene.rebuild() then Renderer.render()
     once per scene in turn (wall time, numpy image out): a burst of load from
     other processes then falls on every scene alike, and the ratios between
     rows (the fitted exponent alpha) do not depend on which row it hit.
"total" = rebuild + render: loaded triangles to an image, without reading
files or compiling.
"""
from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np

import hlbvh_cl.io.scenefile

from .common import cpu_seconds, stopwatch, summary

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
                 builder: str = "hlbvh") -> list[tuple[dict, np.ndarray] | Exception]:
    """Times ``repeats`` rounds of (rebuild + render) of each scene file
    after a warm-up (module docstring): per file, (figures, the last image),
    or the exception that stopped that file (the others go on).  Seconds:
    "runs" lists each run's, "times_s" their {median, min, max}."""
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
            if not isinstance(timing, Exception):
                try:
                    timing.run(timed=run > 0)
                except Exception as error:
                    timings[k] = error
    return [t if isinstance(t, Exception) else (t.result(), t.image) for t in timings]


class _SceneTiming:
    """One scene file loaded on a device, and its timed runs."""

    def __init__(self, path: Path, device_id: str, width: int, height: int, builder: str):
        self.path, self.width, self.height, self.builder = path, width, height, builder
        elapsed = stopwatch()
        loaded = hlbvh_cl.io.scenefile.load(path, device=device_id, builder=builder)
        self.load_s = loaded.load_seconds
        self.first_build_s = elapsed() - self.load_s
        self.scene, self.camera, self.renderer = loaded.scene, loaded.camera, loaded.renderer()
        warm = stopwatch()
        self.renderer.render(self.camera, 1, 1, **SHADING)
        self.render_compile_s = warm()
        self.runs: list[dict] = []
        self.cpu_s = self.wall_s = 0.0
        self.image = None

    def run(self, timed: bool) -> None:
        cpu_before, whole = cpu_seconds(), stopwatch()
        self.scene.rebuild()
        build_s = whole()
        self.image = self.renderer.render(self.camera, self.width, self.height, **SHADING)
        total_s = whole()
        if timed:
            # CPU time over wall time: how many cores the work got (a CPU
            # device's threads run in this process)
            self.cpu_s += cpu_seconds() - cpu_before
            self.wall_s += total_s
            self.runs.append({"build_s": build_s, "render_s": total_s - build_s,
                              "total_s": total_s,
                              "build_device_s": self.scene.stats.device_ms * 1e-3})

    def result(self) -> dict:
        rendered, stats, runs = self.renderer.stats, self.scene.stats, self.runs
        times = {key: summary([r[key] for r in runs]) for key in runs[0]}
        rays = rendered["primary_rays"] + rendered["secondary_rays"]
        return {
            "scene": self.path.name, "device": self.scene.device.id, "builder": self.builder,
            "width": self.width, "height": self.height, **SHADING,
            "triangles": stats.triangles, "meshes": len(self.scene.meshes),
            "nodes": stats.nodes, "sah_cost": stats.sah_cost,
            "primary_rays": int(rendered["primary_rays"]),
            "secondary_rays": int(rendered["secondary_rays"]),
            "repeats": len(runs), "load_s": self.load_s,
            "compile_s": {"build": max(0.0, self.first_build_s - times["build_s"]["median"]),
                          "render": self.render_compile_s},
            "times_s": times, "runs": runs, "cores_used": self.cpu_s / self.wall_s,
            "render_mrays": rays / times["render_s"]["median"] / 1e6,
            "image": {"shape": list(self.image.shape), "mean": float(self.image.mean()),
                      "sha256": hashlib.sha256(self.image.tobytes()).hexdigest()[:16]},
        }


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
