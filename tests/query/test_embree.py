"""Closest hits against Embree (embreex) on the scanned meshes, with random
rays and pinhole-camera rays.  Both work in float32, so they may disagree on
rays that graze an edge; such disagreements must stay below 1e-4 of the rays.
"""
from __future__ import annotations


import numpy as np
import pytest

import hlbvh_cl
import places

rtcs = pytest.importorskip("embreex.rtcore_scene")
from embreex.mesh_construction import TriangleMesh  # noqa: E402

MESHES = places.MESHES
RAYS = 100_000
MAX_DISAGREEMENT = 1e-4   # fraction of rays whose hit/miss may differ
T_RTOL = 1e-4
EMBREE_MISS = 1e37        # embreex leaves tfar here on a miss


class Pair:
    def __init__(self, name: str):
        self.mesh = hlbvh_cl.Mesh.load(MESHES / f"{name}.ply")
        self.scene = hlbvh_cl.Scene([self.mesh])
        self.embree = rtcs.EmbreeScene()
        TriangleMesh(self.embree, self.mesh.vertices, self.mesh.faces)
        self.lo, self.hi = (b.astype(np.float64) for b in self.mesh.bounds)


@pytest.fixture(scope="module", params=["bunny", "armadillo", "lucy"])
def pair(request):
    return Pair(request.param)


def random_rays(pair: Pair, count: int, seed: int):
    rng = np.random.default_rng(seed)
    size = pair.hi - pair.lo
    origins = pair.lo - size + rng.random((count, 3)) * 3 * size
    targets = pair.lo + rng.random((count, 3)) * size
    return origins.astype(np.float32), (targets - origins).astype(np.float32)


def camera_rays(pair: Pair, count: int):
    """A pinhole camera (40 degrees vertical) looking at the mesh from its front-right."""
    width = int(np.sqrt(count * 1.6))
    height = count // width
    centre = (pair.lo + pair.hi) / 2
    radius = np.linalg.norm(pair.hi - pair.lo) / 2
    eye = centre + radius * 2.0 * np.array([0.45, 0.25, 0.86])
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half = np.tan(np.radians(40.0) / 2)
    ys, xs = np.mgrid[0:height, 0:width]
    px = ((xs + 0.5) / width * 2 - 1) * half * width / height
    py = (1 - (ys + 0.5) / height * 2) * half
    directions = forward + px[..., None] * right + py[..., None] * up
    directions = directions.reshape(-1, 3)
    origins = np.broadcast_to(eye, directions.shape)
    return origins.astype(np.float32), directions.astype(np.float32)


@pytest.mark.parametrize("kind", ["random", "camera"])
def test_matches_embree(pair, kind):
    origins, directions = random_rays(pair, RAYS, seed=1) if kind == "random" else camera_rays(pair, RAYS)
    ours = pair.scene.intersect(origins, directions)
    theirs = pair.embree.run(origins, directions, output=1)
    their_hit = theirs["primID"] >= 0
    assert np.all(theirs["tfar"][~their_hit] >= EMBREE_MISS)
    assert 0.05 < their_hit.mean() < 0.98, "the rays should both hit and miss"

    disagree = np.count_nonzero(ours.hit != their_hit)
    assert disagree <= MAX_DISAGREEMENT * len(origins), (
        f"{pair.mesh.name}/{kind}: hit/miss differs on {disagree} of {len(origins)} rays")

    both = ours.hit & their_hit
    np.testing.assert_allclose(ours.t[both], theirs["tfar"][both], rtol=T_RTOL)
    same = both & (ours.prim_id == theirs["primID"])
    # ties (equal t on two triangles, e.g. through a shared edge) are rare
    assert np.count_nonzero(same) >= 0.999 * np.count_nonzero(both)
    assert np.all(ours.geom_id[ours.hit] == 0)
    their_normal = theirs["Ng"] / np.maximum(np.linalg.norm(theirs["Ng"], axis=1, keepdims=True), 1e-30)
    np.testing.assert_allclose(ours.normal[same], their_normal[same], atol=1e-3)
    # float32 barycentrics of grazing rays are uncertain in both (error ~ 1/cos)
    cos = np.abs(np.einsum("ij,ij->i", ours.normal, directions)) / np.linalg.norm(directions, axis=1)
    steep = same & (cos > 0.02)
    assert np.count_nonzero(steep) > 0.9 * np.count_nonzero(same)
    np.testing.assert_allclose(ours.u[steep], theirs["u"][steep], atol=1e-3)
    np.testing.assert_allclose(ours.v[steep], theirs["v"][steep], atol=1e-3)
