"""Scenes that travel: what a Scene pickles as, and the process-wide cache
that builds each scene once per process however many tasks unpickle it.

A Scene pickles as a SceneSpec: its meshes (arrays and names), its instances
(mesh indices and maps) and masks where it has them, its build options and
the device it was asked for (the spec as the caller gave it, never OpenCL
objects).  Unpickling looks the spec's content key up in the cache and
builds the Scene only when it is not there, so a worker of a cluster
(hlbvh_cl.distributed.dask) that runs a thousand tasks on one scene builds it once.
Each unpickling gets a Scene object of its own, a view over the cached
scene's trees (Scene.view): a view that changes (update_vertices,
set_transforms, rebuild) first builds trees of its own, so no change
reaches the cache or another holder, as with any copy.
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np


#: Scenes the cache keeps (the least recently used goes first): each holds
#: its trees on the device.
CACHE_SIZE = 4


@dataclass(frozen=True)
class SceneSpec:
    """Everything a Scene is built from."""

    meshes: tuple
    instances: tuple | None  # (mesh indices (K,) int32, maps (K, 3, 4) float64), or None
    masks: np.ndarray | None  # uint32, or None (every bit)
    builder: str
    morton_bits: int
    device: str | None
    key: str  # content hash of all of the above
    spheres: np.ndarray | None = None  # (S, 4) float64 centres and radii, or None
    compact: bool = False

    @classmethod
    def make(cls, meshes, instances, masks, builder: str, morton_bits: int,
             device: str | None, spheres: np.ndarray | None = None,
             compact: bool = False) -> "SceneSpec":
        digest = hashlib.blake2b(digest_size=20)
        for mesh in meshes:
            # the shading normals too, given or not, and face_normals: two
            # scenes of one geometry shaded otherwise are two scenes (the
            # cache had handed back the first for the second); computed
            # normals follow from the arrays, and are not computed here
            given = mesh.has_file_normals
            for array in (mesh.vertices, mesh.faces) + ((mesh.normals,) if given else ()):
                digest.update(str(array.shape).encode())
                digest.update(np.ascontiguousarray(array).data)
            digest.update(repr((mesh.name, given, mesh.face_normals)).encode())
        for part in ((instances or ()) + ((masks,) if masks is not None else ())
                     + ((spheres,) if spheres is not None else ())):
            digest.update(str(part.shape).encode())
            digest.update(np.ascontiguousarray(part).data)
        digest.update(repr((instances is None, masks is None, spheres is None, builder,
                            morton_bits, device, compact)).encode())
        return cls(tuple(meshes), instances, masks, builder, morton_bits, device,
                   digest.hexdigest(), spheres, compact)

    def __dask_tokenize__(self):
        return ("hlbvh_cl.SceneSpec", self.key)

    def arguments(self) -> tuple[list, dict]:
        """Scene's positional and keyword arguments for this spec."""
        pairs = None if self.instances is None else \
            [(int(m), t) for m, t in zip(*self.instances)]
        return [list(self.meshes)], dict(device=self.device, builder=self.builder,
                                         morton_bits=self.morton_bits, instances=pairs,
                                         masks=self.masks, spheres=self.spheres,
                                         compact=self.compact)


_cache: OrderedDict = OrderedDict()
_cache_lock = threading.Lock()
_building: dict = {}


def restore(spec: SceneSpec, scene_class):
    """A view (Scene.view) of the Scene of ``spec``: the cached one, or a
    new one built (by ``scene_class``) and cached.  Concurrent restores of
    one spec build it once (the others wait).  The cached scene itself is
    never handed out, so it never changes."""
    with _cache_lock:
        if spec.key in _cache:
            _cache.move_to_end(spec.key)
            return _cache[spec.key].view()
        lock = _building.setdefault(spec.key, threading.Lock())
    with lock:
        with _cache_lock:
            if spec.key in _cache:
                return _cache[spec.key].view()
        try:
            args, kwargs = spec.arguments()
            scene = scene_class(*args, **kwargs)
        except BaseException:  # a device gone, Ctrl-C: the lock's entry goes too
            with _cache_lock:
                _building.pop(spec.key, None)
            raise
        with _cache_lock:
            _cache[spec.key] = scene
            _building.pop(spec.key, None)
            while len(_cache) > CACHE_SIZE:
                _cache.popitem(last=False)
        return scene.view()


def cached_count() -> int:
    """How many scenes the cache holds (for tests)."""
    with _cache_lock:
        return len(_cache)


def cached_scenes() -> list:
    """Views (Scene.view) of the scenes the cache holds, the least recently
    used first: for benchmarks and tests that read them (their stats, say);
    the cached scenes themselves are never handed out."""
    with _cache_lock:
        return [scene.view() for scene in _cache.values()]


def building_keys() -> set[str]:
    """The content keys of the scenes that restore is building now (for
    tests: a build that failed leaves none behind)."""
    with _cache_lock:
        return set(_building)


def clear() -> None:
    """Empty the cache (its scenes stay alive while anyone holds them)."""
    with _cache_lock:
        _cache.clear()
