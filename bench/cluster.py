"""Work spread over a local Dask cluster against the same work in one
process: what hlbvh_cl.distributed.dask costs.

    python -m bench.cluster [--quick] [--devices pocl] [--repeats N] [--docs] [--no-progress]

  a. frames: hlbvh_cl.distributed.dask.render_frames of F frames (the scene file's
     camera turned about its target, W x H, diffuse with shadows, one task a
     frame) on a LocalCluster of 1 and of 2 worker processes with one thread
     each, against one process that builds the Scene and renders the same
     frames with a Renderer.  A cluster round starts with nothing of the
     scene on the workers: it ships the scene (a scatter to every worker),
     each worker builds it, renders its frames, and the images come back.
  b. rays: hlbvh_cl.distributed.dask.intersect over C chunks of R camera rays (tiles of
     rows of one image) that da.map_blocks makes on the workers; each
     chunk's hits are reduced where they were traced (hits, and a sum of
     prim ids), so little comes back.  One process: a Scene built, then the
     same tiles made and traced in turn.
  c. overhead per task: N tasks that do nothing, submitted and gathered, on
     each warm cluster.

The clusters' workers start with hlbvh_cl.distributed.dask.WORKER_CONFIG (glibc's own
memory trimming, as docs/dask.md advises).  Starting a cluster is not timed,
nor is compiling the kernels: every process first builds the scene, renders
and traces a little (once per process), and then forgets the scene.  Rounds alternate between one process and the
cluster, and each cluster size is set against the one-process rounds beside
its own.  Where the time goes: the ship (the scatter, timed apart in the
round), the workers' builds (their Scene.stats), and the excess over one
process per task.

Writes <out>/cluster.json; with --docs also the cluster section of
bench/RESULTS.md.
"""
from __future__ import annotations

import math
import sys
from dataclasses import asdict, dataclass, replace

import numpy as np

import hlbvh_cl
import hlbvh_cl.io.scenefile
from hlbvh_cl import travel

from . import common
from .common import (BENCH, SCENES, arguments, devices_or_exit, finish, machine_info, progress,
                     say, spread, stopwatch, summary, table)

#: the issue's targets: 2 workers' wall time over one process's
TARGETS = {"frames_ratio": 1.25, "rays_ratio": 1.25}
SECTION = "cluster"
WORKERS = (1, 2)


@dataclass(frozen=True)
class Config:
    scene: str                   # a scene file in scenes/
    frames: int                  # a
    resolution: tuple[int, int]  # a: (width, height)
    image: tuple[int, int]       # b: the rays' image, (width, height)
    chunks: int                  # b: tiles of image rows
    noop_tasks: int              # c
    repeats: int                 # rounds of each side, per cluster size


FULL = Config("reference.toml", 64, (1280, 720), (4096, 4096), 16, 200, 3)
QUICK = Config("bunny_small.toml", 8, (320, 180), (512, 512), 4, 50, 1)


# ---------------------------------------------------------------- the work

def orbit(camera: hlbvh_cl.Camera, count: int) -> list[hlbvh_cl.Camera]:
    """``count`` cameras on the circle of ``camera``'s eye about the vertical
    through its target, a full turn."""
    offset = np.subtract(camera.eye, camera.target)
    out = []
    for angle in np.linspace(0, 2 * np.pi, count, endpoint=False):
        c, s = math.cos(angle), math.sin(angle)
        turned = (c * offset[0] + s * offset[2], offset[1], -s * offset[0] + c * offset[2])
        out.append(hlbvh_cl.Camera(tuple(np.add(camera.target, turned)), camera.target,
                                   camera.up, camera.fov_deg))
    return out


def tile_rays(pinhole: np.ndarray, width: int, height: int, rows: int,
              block_id=None) -> np.ndarray:
    """float32 (rows, width, 6): the packed primary rays of image rows
    [k * rows, (k + 1) * rows) for block k, as Camera.rays makes them."""
    first = block_id[0] * rows
    f32 = np.float32
    ys, xs = np.mgrid[first:first + rows, 0:width].astype(f32)
    sx = (f32(2) * (xs + f32(0.5)) / f32(width) - f32(1))[..., None]
    sy = (f32(1) - f32(2) * (ys + f32(0.5)) / f32(height))[..., None]
    out = np.empty((rows, width, 6), f32)
    out[..., :3] = pinhole["eye"]
    out[..., 3:] = pinhole["forward"] + sx * pinhole["right"] + sy * pinhole["up"]
    return out


def reduce_hits(hits) -> tuple:
    """What a round of part b keeps of its hits: how many rays hit, and the
    sum of their prim ids (misses add -1 each)."""
    return (hits.geom_id >= 0).sum(), hits.prim_id.astype(np.int64).sum()


def _noop(x):
    return x


def _forget() -> int:
    """On a worker: drop the scenes and renderers it built, so that the next
    round builds again.  Returns how many scenes it held."""
    import hlbvh_cl.distributed.dask as hd
    held = travel.cached_count()
    hd.forget()
    return held


def _warm(scene, camera: hlbvh_cl.Camera, rays: np.ndarray) -> None:
    """A small render and trace of ``scene`` (a Scene, or what hlbvh_cl.distributed.dask
    ships): every kernel the rounds run gets compiled."""
    if not isinstance(scene, hlbvh_cl.Scene):
        with scene.scene() as shipped:
            _warm(shipped, camera, rays)
        return
    hlbvh_cl.Renderer(scene).render(camera, 16, 16)
    scene.intersect(rays)


def _builds_ms() -> list[float]:
    """On a worker: the build wall ms of each scene it holds."""
    return [float(s.stats.wall_ms) for s in travel.cached_scenes()]


class Work:
    """One configuration's work, done either way."""

    def __init__(self, config: Config, device: str):
        self.config, self.device = config, device
        description = hlbvh_cl.io.scenefile.read(SCENES / config.scene)
        geometries = description.geometries()
        self.meshes = [m for m, _ in geometries]
        self.colors = [c for _, c in geometries]
        self.light = description.light
        self.cameras = orbit(description.camera, config.frames)
        width, height = config.image
        if height % config.chunks:
            raise SystemExit(f"the image's {height} rows do not split into {config.chunks} tiles")
        self.rows = height // config.chunks
        self.pinhole = description.camera.pinhole(width, height)
        self.scene = hlbvh_cl.Scene(self.meshes, device=device)  # the client's, shipped

    @property
    def rays(self) -> int:
        return self.config.image[0] * self.config.image[1]

    # one process
    def frames_here(self) -> list:
        scene = hlbvh_cl.Scene(self.meshes, device=self.device)
        renderer = hlbvh_cl.Renderer(scene, colors=self.colors, light=self.light)
        return [renderer.render(c, *self.config.resolution) for c in self.cameras]

    def rays_here(self) -> tuple:
        scene = hlbvh_cl.Scene(self.meshes, device=self.device)
        found = np.zeros(2, np.int64)
        width, height = self.config.image
        for k in range(self.config.chunks):
            hits = scene.intersect(tile_rays(self.pinhole, width, height, self.rows, (k, 0, 0)))
            found += reduce_hits(hits)
        return tuple(int(x) for x in found)

    # the cluster
    def frames_there(self, client) -> list:
        import hlbvh_cl.distributed.dask as hd
        return hd.render_frames(self.scene, self.cameras, *self.config.resolution, client,
                                colors=self.colors, light=self.light, progress=False)

    def rays_there(self, client) -> tuple:
        import dask
        import dask.array as da

        import hlbvh_cl.distributed.dask as hd
        width, height = self.config.image
        rays = da.map_blocks(tile_rays, self.pinhole, width, height, self.rows,
                             chunks=((self.rows,) * self.config.chunks, (width,), (6,)),
                             dtype=np.float32, meta=np.empty((0, 0, 0), np.float32))
        return tuple(int(x) for x in dask.compute(*reduce_hits(hd.intersect(self.scene, rays,
                                                                            client=client))))

    def warm_up(self, client=None) -> None:
        """Compiles what the rounds run, in this process or on every worker
        (then forgetting the scene there)."""
        rays = tile_rays(self.pinhole, *self.config.image, 1, (0, 0, 0))
        if client is None:
            _warm(self.scene, self.cameras[0], rays)
            return
        import hlbvh_cl.distributed.dask as hd
        shipped = hd.ship(self.scene, client)
        client.gather([client.submit(_warm, shipped, self.cameras[0], rays, workers=[w],
                                     allow_other_workers=False, pure=False)
                       for w in client.scheduler_info()["workers"]])
        self.forget(client)

    def record_ms(self, repeats: int = 3) -> float:
        """The ms a chunk's hits take to become one record array (the dask
        path's copy, which one process does not make), here."""
        import hlbvh_cl.distributed.dask as hd
        hits = self.scene.intersect(tile_rays(self.pinhole, *self.config.image, self.rows,
                                              (0, 0, 0)))
        times = []
        for _ in range(repeats):
            elapsed = stopwatch()
            hd.records(hits, hd.HITS)
            times.append(elapsed() * 1e3)
        return summary(times)["median"]

    def forget(self, client) -> None:
        import hlbvh_cl.distributed.dask as hd
        client.run(_forget)
        hd.unship(self.scene)


# ---------------------------------------------------------------- rounds

def cluster_round(work: Work, client, part: str) -> dict:
    """One round on the cluster from nothing of the scene there: the ship
    timed apart, then the part's work (which finds the scene shipped)."""
    import hlbvh_cl.distributed.dask as hd
    work.forget(client)
    elapsed = stopwatch()
    hd.ship(work.scene, client)
    ship_s = elapsed()
    answer = work.frames_there(client) if part == "frames" else work.rays_there(client)
    total_s = elapsed()
    builds = [ms for found in client.run(_builds_ms).values() for ms in found]
    return {"seconds": total_s, "ship_s": ship_s, "build_ms": builds, "answer": answer}


def bench_workers(work: Work, workers: int, repeats: int, bar) -> dict:
    """Parts a, b and c on a LocalCluster of ``workers`` processes, each
    round beside a one-process round of the same work."""
    import dask
    from distributed import Client, LocalCluster

    import hlbvh_cl.distributed.dask as hd
    out = {"workers": workers}
    with dask.config.set(hd.WORKER_CONFIG):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0")
    with cluster, Client(cluster) as client:
        work.warm_up(client)
        for part, here in (("frames", work.frames_here), ("rays", work.rays_here)):
            single, spread_rounds = [], []
            for _ in range(repeats):
                elapsed = stopwatch()
                expected = here()
                single.append(elapsed())
                found = cluster_round(work, client, part)
                spread_rounds.append(found)
                bar.update()
            identical = all(_same(r["answer"], expected) for r in spread_rounds)
            out[part] = _part_figures(part, work, single, spread_rounds, identical)
        elapsed = stopwatch()
        client.gather(client.map(_noop, range(work.config.noop_tasks), pure=False))
        out["noop_task_ms"] = elapsed() * 1e3 / work.config.noop_tasks
        work.forget(client)
    say(f"  {workers} worker(s): frames {out['frames']['ratio']:.2f}x, rays "
        f"{out['rays']['ratio']:.2f}x one process; a task that does nothing "
        f"{out['noop_task_ms']:.2f} ms")
    return out


def _same(a, b) -> bool:
    if isinstance(a, list):
        return len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    return tuple(a) == tuple(b)


def _part_figures(part: str, work: Work, single: list, rounds: list, identical: bool) -> dict:
    config = work.config
    spread_s = [r["seconds"] for r in rounds]
    tasks = config.frames if part == "frames" else config.chunks
    here, there = summary(single), summary(spread_s)
    out = {"single_s": here, "cluster_s": there, "ratio": there["median"] / here["median"],
           "tasks": tasks, "identical": identical,
           "ship_s": summary([r["ship_s"] for r in rounds]),
           "worker_build_ms": summary([ms for r in rounds for ms in r["build_ms"]] or [0.0]),
           "excess_per_task_ms": (there["median"] - here["median"]) * 1e3 / tasks}
    if part == "frames":
        out["frames_per_s"] = {"single": config.frames / here["median"],
                               "cluster": config.frames / there["median"]}
        width, height = config.resolution
        out["gathered_mib"] = config.frames * width * height * 3 / 2**20
    else:
        out["mrays"] = {"single": common.rates(work.rays, single),
                        "cluster": common.rates(work.rays, spread_s)}
    return out


# ---------------------------------------------------------------- report

def _met(ratio: float, target: float) -> str:
    return "yes" if ratio <= target else "no"


def _tables(results: dict) -> list[tuple[str, list[str], list[list]]]:
    config = results["config"]
    width, height = config["resolution"]
    rows_a, rows_b, rows_c = [], [], []
    for r in results["clusters"]:
        a, b, n = r["frames"], r["rays"], r["workers"]
        target = TARGETS["frames_ratio"] if n == 2 else None
        rows_a.append([n, spread(a["single_s"], digits=2), spread(a["cluster_s"], digits=2),
                       f"{a['frames_per_s']['single']:.1f}", f"{a['frames_per_s']['cluster']:.1f}",
                       f"{a['ratio']:.2f}x", _met(a["ratio"], target) if target else "-",
                       "yes" if a["identical"] else "NO"])
        target = TARGETS["rays_ratio"] if n == 2 else None
        rows_b.append([n, spread(b["single_s"], digits=2), spread(b["cluster_s"], digits=2),
                       f"{b['mrays']['single']['median']:.2f}",
                       f"{b['mrays']['cluster']['median']:.2f}", f"{b['ratio']:.2f}x",
                       _met(b["ratio"], target) if target else "-",
                       "yes" if b["identical"] else "NO"])
        for part in ("frames", "rays"):
            p = r[part]
            rows_c.append([n, part, p["tasks"], f"{p['ship_s']['median'] * 1e3:.0f}",
                           f"{p['worker_build_ms']['median']:.0f}",
                           f"{p['excess_per_task_ms']:.1f}",
                           f"{r['noop_task_ms']:.2f}"])
    return [
        (f"a. render_frames: {config['frames']} frames of {config['scene']} at {width}x{height}, "
         f"one task a frame, scene shipping and builds included; s per round, median (min-max) "
         f"of {config['repeats']} (target: 2 workers <= {TARGETS['frames_ratio']:g}x one process)",
         ["workers", "one process s", "cluster s", "one process frames/s", "cluster frames/s",
          "cluster / one", "target met", "identical"], rows_a),
        (f"b. intersect over dask arrays: {config['chunks']} chunks of "
         f"{results['rays'] // config['chunks']:,} camera rays of {config['scene']} made on "
         f"the workers, hits reduced there; s per round (target: 2 workers <= "
         f"{TARGETS['rays_ratio']:g}x one process)",
         ["workers", "one process s", "cluster s", "one process Mrays/s", "cluster Mrays/s",
          "cluster / one", "target met", "identical"], rows_b),
        ("c. where the overhead goes: the scatter of the scene to every worker, a worker's "
         "build, the cluster's excess over one process per task, and a task that does nothing "
         "(submit to result)",
         ["workers", "part", "tasks", "ship ms", "worker build ms", "excess ms / task",
          "empty task ms"], rows_c)]


def _notes(results: dict) -> list[str]:
    return [f"Of part b's excess, each chunk's hits becoming one record array (the dask path's "
            f"copy, which one process does not make) took {results['record_ms_per_chunk']:.1f} "
            "ms a chunk in one process."]


def format_results(results: dict, markdown: bool = False) -> str:
    tables = _tables(results)
    if not markdown:
        return "\n\n".join([table(h, rows, title) for title, h, rows in tables]
                           + _notes(results))
    from .report import md_table
    machine = results["machine"]
    lines = [f"<!-- begin {SECTION} -->", "", "## Dask cluster", "",
             f"Measured on {machine['date']} with `{results['command']}` (bench/cluster.py; its "
             f"docstring says how) on {results['device']}, {machine['cpus']} CPUs, load average "
             + ", ".join(f"{x:.2f}" for x in machine["loadavg"])
             + " at the start; above the CPU count means other processes ran too. Every worker "
             "process's OpenCL CPU device uses all the cores, so on one machine more workers "
             "share the same cores: no speed-up is to be had here, and what the figures show "
             "is the cost of spreading the work.", ""]
    for title, headers, rows in tables:
        lines += [f"{title}:", "", md_table(headers, rows), ""]
    lines += _notes(results) + ["", "*JSON: `cluster.json`*", "", f"<!-- end {SECTION} -->"]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- the command

def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["--repeats"], {"type": int, "default": None,
                                      "help": "rounds of each side per cluster size"}))
    config = QUICK if args.quick else FULL
    if args.repeats is not None:
        if args.repeats < 1:
            raise SystemExit(f"--repeats must be at least 1, got {args.repeats}")
        config = replace(config, repeats=args.repeats)
    elapsed = stopwatch()
    device = devices_or_exit(args.devices or "pocl")[0].id
    say(f"device: {device}; {config.scene}: {config.frames} frames at "
        f"{config.resolution[0]}x{config.resolution[1]}, {config.chunks} chunks of "
        f"{config.image[0] * config.image[1] // config.chunks:,} rays")
    work = Work(config, device)
    work.warm_up()
    record_ms = work.record_ms()
    results = {"command": " ".join(["python -m bench.cluster",
                                     *(sys.argv[1:] if argv is None else argv)]),
               "config": asdict(config), "quick": args.quick, "machine": machine_info(),
               "device": device, "targets": TARGETS, "rays": work.rays,
               "triangles": int(sum(m.triangle_count for m in work.meshes)),
               "record_ms_per_chunk": record_ms, "clusters": []}
    with progress(len(WORKERS) * 2 * config.repeats, "cluster bench",
                  enabled=not args.no_progress) as bar:
        for workers in WORKERS:
            results["clusters"].append(bench_workers(work, workers, config.repeats, bar))
    print(format_results(results))
    finish(results, "cluster", args, elapsed)
    if args.docs:
        common.write_section(BENCH / "RESULTS.md", format_results(results, markdown=True),
                             SECTION)
    return results


if __name__ == "__main__":
    main()
