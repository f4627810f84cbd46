"""Signed-distance samples for every mesh in a folder, made across a Dask
cluster: per mesh, N points with their signed distances
(Scene.signed_distance, negative inside), written as OUTPUT/<mesh>.npz with
``points`` float32 (N, 3) and ``sdf`` float32 (N,).

    python examples/sdf_dataset.py [FOLDER] [--output sdf_dataset] [--points 100000]
                                   [--near 0.5] [--sigma 0.01] [--seed 0]
                                   [--scheduler tcp://host:8786] [--workers 2] [--device pocl]

FOLDER (default scenes/meshes) is searched recursively for .ply, .obj, .stl,
.off and .glb files.  Of each mesh's points, the fraction --near lies near
the surface (a point of it, drawn by area, moved by a normal random offset
of --sigma times the box's diagonal); the rest are uniform in the mesh's
box grown by 10% (its sides 10% longer).  A mesh's points depend on the
seed and the file's name alone, so a rerun writes the same files.

One task per mesh, on a LocalCluster of --workers workers (one thread each:
an OpenCL CPU device uses every core) or on the cluster whose scheduler
--scheduler names.  A worker loads the mesh, builds its Scene and writes
the file, so FOLDER and OUTPUT must be visible to the workers (a shared
filesystem; on a LocalCluster they are).
"""
from __future__ import annotations

import argparse
import sys
import time
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if (ROOT / "hlbvh_cl" / "__init__.py").is_file():  # run from a checkout: use its hlbvh_cl
    sys.path.insert(0, str(ROOT))

import hlbvh_cl  # noqa: E402

SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb")
GROW = 0.10  # the uniform points' box: the mesh's, its sides this much longer


def sample_points(mesh: hlbvh_cl.Mesh, count: int, near: float, sigma: float,
                  rng: np.random.Generator) -> np.ndarray:
    """float32 (count, 3): near the surface first, then uniform in the grown box."""
    lo, hi = (np.asarray(b, np.float64) for b in mesh.bounds)
    size = hi - lo
    n_near = int(round(near * count))
    corners = mesh.vertices[mesh.faces].astype(np.float64)  # (F, 3, 3)
    areas = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                    corners[:, 2] - corners[:, 0]), axis=1)
    faces = rng.choice(len(areas), n_near, p=areas / areas.sum())
    a, b = rng.random((2, n_near, 1))
    flip = a + b > 1  # folded back into the triangle: uniform over its area
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    c = corners[faces]
    surface = c[:, 0] + a * (c[:, 1] - c[:, 0]) + b * (c[:, 2] - c[:, 0])
    offsets = rng.normal(scale=sigma * np.linalg.norm(size), size=(n_near, 3))
    uniform = lo - GROW / 2 * size + rng.random((count - n_near, 3)) * (1 + GROW) * size
    return np.concatenate([surface + offsets, uniform]).astype(np.float32)


def make_samples(path: str, output: str, count: int, near: float, sigma: float, seed: int,
                 device: str | None) -> dict:
    """One task: a mesh's points and signed distances written to OUTPUT/<stem>.npz."""
    started = time.perf_counter()
    mesh = hlbvh_cl.Mesh.load(path)
    scene = hlbvh_cl.Scene([mesh], device=device)
    rng = np.random.default_rng([seed, zlib.crc32(Path(path).name.encode())])
    points = sample_points(mesh, count, near, sigma, rng)
    sdf = scene.signed_distance(points)
    target = Path(output) / f"{Path(path).stem}.npz"
    np.savez(target, points=points, sdf=sdf)
    return {"mesh": Path(path).name, "file": str(target), "triangles": mesh.triangle_count,
            "inside": float(np.mean(sdf < 0)), "seconds": time.perf_counter() - started}


def mesh_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.suffix.lower() in SUFFIXES)


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", nargs="?", type=Path, default=ROOT / "scenes" / "meshes")
    parser.add_argument("--output", type=Path, default=Path("sdf_dataset"))
    parser.add_argument("--points", type=int, default=100_000, help="points per mesh")
    parser.add_argument("--near", type=float, default=0.5,
                        help="the fraction of points near the surface")
    parser.add_argument("--sigma", type=float, default=0.01,
                        help="near points' offset, as a fraction of the box's diagonal")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scheduler", default=None,
                        help="a Dask scheduler's address (default: a LocalCluster)")
    parser.add_argument("--workers", type=int, default=2, help="LocalCluster workers")
    parser.add_argument("--device", default=None,
                        help="OpenCL device of every worker (default: each worker's own choice)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.points < 1 or not 0 <= args.near <= 1 or args.sigma < 0:
        parser.error("--points must be >= 1, --near in [0, 1] and --sigma >= 0")
    files = mesh_files(args.folder)
    if not files:
        parser.error(f"no mesh files ({', '.join(SUFFIXES)}) under {args.folder}")
    args.output.mkdir(parents=True, exist_ok=True)

    import dask
    from distributed import Client, LocalCluster, progress

    import hlbvh_cl.distributed.dask
    cluster = None
    if args.scheduler is None:
        with dask.config.set(hlbvh_cl.distributed.dask.WORKER_CONFIG):
            cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1,
                                   processes=True, dashboard_address=":0")
    try:
        with Client(args.scheduler or cluster) as client:
            futures = client.map(make_samples, [str(f) for f in files],
                                 output=str(args.output.resolve()), count=args.points,
                                 near=args.near, sigma=args.sigma, seed=args.seed,
                                 device=args.device, pure=False)
            if not args.no_progress:
                progress(futures)
            done = client.gather(futures)
    finally:
        if cluster is not None:
            cluster.close()
    print()
    for r in done:
        print(f"{r['mesh']:>24}: {r['triangles']:>9,} triangles, {r['inside']:6.1%} of the "
              f"points inside, {r['seconds']:.2f} s -> {r['file']}")
    return done


if __name__ == "__main__":
    main()
