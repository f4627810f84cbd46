"""Ray and point queries over dask arrays, and frames rendered across a Dask
cluster (``pip install 'hlbvh_cl[dask]'``; docs/dask.md).

    import dask, dask.array as da, hlbvh_cl.distributed.dask
    rays = da.from_array(packed, chunks=(1 << 20, 6))       # (N, 6), or origins and directions
    hits = hlbvh_cl.distributed.dask.intersect(scene, rays)              # a Hits of dask arrays
    t, prim = dask.compute(hits.t, hits.prim_id)             # one traversal per chunk
    images = hlbvh_cl.distributed.dask.render_frames(scene, cameras, 1280, 720)

The queries take what the Scene methods take (rays (..., 3) with their
origins broadcast, packed (..., 6), points (..., 3); numpy arrays and lists
too) chunked along the leading dimensions, and return dask arrays chunked as
the rays or points are: one task per chunk.  Each task runs one query on its
chunk and returns a record array (intersect, closest_points) whose fields the
returned Hits or ClosestPoints hold as dask arrays.  intersect_all's hits per
ray are known only once traced: its hit arrays have chunks of unknown length,
and its offsets come from a count of each chunk.

The scene enters a graph once: scattered to every worker of a distributed
client (the given one, else the current default), else as one key of the
graph.  Either way it travels as its SceneSpec (hlbvh_cl.travel) and is built
where a task first needs it, once per process.  Scattering to every worker
rather than one keeps a copy where a killed worker's tasks are rerun.
ship does this ahead of the queries; unship (on the client) and forget (in
a worker) drop what a process keeps of it, so that the next use ships and
builds it again (bench/cluster.py times rounds from nothing that way).

Bad input raises the error the Scene method raises, naming the row by its
index in the whole array: a chunk's error is renamed from the chunk's index.
"""
from __future__ import annotations

import os
import re
import sys
import threading
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path

import dask
import dask.array as da
import numpy as np
from dask.array.core import unify_chunks

from ..core import inputs
from .. import travel
from ..query.all_hits import HIT_FIELDS as ALL_HIT_FIELDS
from ..query.all_hits import AllHits, check_max_hits
from ..query.points import CLOSEST_FIELDS, ClosestPoints, check_max_distance
from ..query.rays import HIT_FIELDS, Hits
from ..render.camera import Camera
from ..render.renderer import Renderer, check_settings
from ..render.settings import AO_SAMPLES, RR_DEPTH
from ..query.results import ResultPool
from ..scene import Scene

__all__ = ["closest_points", "contains", "count_intersections", "intersect", "intersect_all",
           "occluded",
           "render_frames", "signed_distance", "winding_number"]


def _record(fields: dict) -> np.dtype:
    """The record dtype of a query's per-ray fields (query.HIT_FIELDS,
    points.CLOSEST_FIELDS: dtype and values per item), which one chunk's
    task returns in one array."""
    return np.dtype([(name, dtype) if n == 1 else (name, dtype, (n,))
                     for name, (dtype, n) in fields.items()])


HITS = _record(HIT_FIELDS)
#: intersect_all's hits as one record array per chunk, with their rays.
HIT_LIST = _record({"ray_index": (np.int64, 1),
                    **{name: (dtype, 1) for name, dtype in ALL_HIT_FIELDS.items()}})
CLOSEST = _record(CLOSEST_FIELDS)

#: Dask configuration for the clusters a client starts (LocalCluster):
#: their workers keep glibc's default trimming.  Dask's nanny sets
#: MALLOC_TRIM_THRESHOLD_, which turns off glibc's adaptive mmap threshold, so
#: every large temporary of a query is mapped and faulted in again on each
#: call.  ``with dask.config.set(WORKER_CONFIG): LocalCluster(...)``
WORKER_CONFIG = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}

#: Renderers a process keeps (per scene, colours and light): each holds its
#: image buffers on the device.
RENDERERS = 4


# ---------------------------------------------------------------- the scene in a graph

class Shipped:
    """A scene as tasks get it.  In the process that made it, the Scene
    itself; pickled, its SceneSpec alone, built where a task asks for it
    (hlbvh_cl.travel: once per process)."""

    def __init__(self, spec: travel.SceneSpec, scene: Scene | None = None):
        self.spec, self._scene = spec, scene

    def __reduce__(self):
        return (Shipped, (self.spec,))

    def __dask_tokenize__(self):
        return ("hlbvh_cl.distributed.dask.scene", self.spec.key)

    @contextmanager
    def scene(self):
        """The scene a task queries, for as long as it queries it.  A scene
        changed since the graph was made answers for its old content, as
        workers do: the Scene itself only while it holds that content, its
        lock held from the check to the task's end (its queries hold it
        throughout anyway), so that no change comes in between."""
        local = self._scene
        if local is not None:
            with local.borrow() as built:
                if built.spec.key == self.spec.key:
                    yield local
                    return
        yield _task_scene(self.spec)


_views: OrderedDict = OrderedDict()
_views_lock = threading.Lock()


def _task_scene(spec: travel.SceneSpec) -> Scene:
    """The one Scene that this process's tasks use for ``spec``: a view
    (hlbvh_cl.travel) that they share, as they only query it, so that they
    share its query buffers and renderers (task_renderer) too, as tasks on one
    scene object would."""
    with _views_lock:
        if spec.key in _views:
            _views.move_to_end(spec.key)
            return _views[spec.key]
    view = travel.restore(spec, Scene)
    with _views_lock:
        view = _views.setdefault(spec.key, view)
        while len(_views) > travel.CACHE_SIZE:
            _views.popitem(last=False)
    return view


def _current_client(client=None):
    """The distributed client to use: the given one (a
    dask.distributed.Client, else a TypeError naming it), else the default
    one if distributed is in use, else None (dask's local schedulers)."""
    if client is not None:
        from distributed import Client
        if not isinstance(client, Client):
            raise TypeError(f"client must be a dask.distributed.Client (or None: the default "
                            f"client, else dask's local threads), got {type(client).__name__}")
        return client
    if "distributed" not in sys.modules:
        return client
    from distributed import default_client
    try:
        return default_client()
    except ValueError:
        return None


_scattered: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_scattered_lock = threading.Lock()


def ship(scene, client=None):
    """What the tasks take as the scene (a Shipped): a one-key Delayed, or
    on a cluster (``client``) a future of it scattered to every worker.  A
    scene is scattered once per client and content, and stays while the
    scene lives (or until unship); the queries ship it themselves, so a
    call of one's own only scatters it sooner (a benchmark times the
    scatter apart).  Each scatter gets a key of its own: a key used again
    while the cluster still releases its last use can be lost."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a hlbvh_cl.Scene, got {type(scene).__name__}")
    with scene.borrow() as built:
        shipped = Shipped(built.spec, scene)
    if client is None:
        return dask.delayed(shipped, pure=True)
    with _scattered_lock:
        held = _scattered.setdefault(scene, {})
        key, future = held.get(client.id, (None, None))
        if key != shipped.spec.key or future.status != "finished":
            future = client.scatter(shipped, broadcast=True, hash=False)
            held[client.id] = (shipped.spec.key, future)
        return future


def unship(scene) -> None:
    """Forget the futures ``scene`` was scattered as (ship): the next query
    on a cluster scatters it again."""
    with _scattered_lock:
        _scattered.pop(scene, None)


def forget() -> None:
    """Drop what this process keeps of the scenes its tasks were shipped:
    their shared views, their renderers (task_renderer) and the scenes
    hlbvh_cl.travel cached, so that the next task on a scene builds it
    again.  Run on a worker (client.run(forget)), a benchmark's next round
    starts from nothing of the scene there."""
    with _views_lock:
        _views.clear()
    with _renderers_lock:
        _renderers.clear()
    travel.clear()


# ---------------------------------------------------------------- inputs

def _shape_only(array: da.Array) -> np.ndarray:
    """A numpy array of ``array``'s shape and dtype that holds no memory: the
    local checks of shapes and dtypes run on it, with their own messages."""
    return np.broadcast_to(np.zeros((), array.dtype), array.shape)


def vectors(name: str, value, width: int = 3) -> da.Array:
    """(..., width) rows as a dask array whose last axis is one chunk; shape
    and dtype errors as the Scene methods raise them."""
    if isinstance(value, da.Array):
        inputs.vectors(name, _shape_only(value), width)
        array = value
    else:
        given = inputs.vectors(name, value, width)
        chunks = ("auto",) * (given.ndim - 1) + (-1,)
        array = da.from_array(given, chunks=chunks)
    return array.rechunk({array.ndim - 1: -1})


def _per_ray(name: str, value, lead: tuple) -> da.Array:
    """A per-ray array (tmin, tmax, mask) broadcast to the rays' leading
    shape, with a last axis of 1 that lines it up with the rays' (..., 3)."""
    array = value if isinstance(value, da.Array) else da.from_array(np.asarray(value))
    empty = np.zeros((0,), array.dtype)
    if name == "mask":
        inputs.ray_masks(empty, (0,))
    else:
        inputs.numeric_array(name, empty)
    inputs.check_per_ray_shape(name, array.shape, lead)
    return da.broadcast_to(array, lead)[..., None]


def _starts(chunks: tuple) -> tuple:
    return tuple(tuple(np.concatenate([[0], np.cumsum(c)[:-1]]).tolist()) for c in chunks)


def _blocks(block_fn, arrays: dict, shipped, dtype: np.dtype, lead_ndim: int, **constants):
    """``block_fn`` over the blocks of ``arrays`` (name -> dask array, right-
    aligned as numpy broadcasts) and the scene: an array of the leading
    chunks, each block knowing where it lies (for the names in errors)."""
    ndim = lead_ndim + 1
    pairs = []
    for array in arrays.values():
        pairs += [array, tuple(range(ndim - array.ndim, ndim))]
    chunks, aligned = unify_chunks(*pairs)
    out_chunks = tuple(chunks[k] for k in range(lead_ndim))
    own = {name: a.shape[:-1] for name, a in zip(arrays, aligned)}
    return da.map_blocks(block_fn, *aligned, shipped, names=tuple(arrays), own=own,
                         starts=_starts(out_chunks), dtype=dtype, drop_axis=ndim - 1,
                         meta=np.empty((0,) * lead_ndim, dtype), **constants)


# ---------------------------------------------------------------- errors

_LABEL = re.compile(r"\b(origins|directions|rays|points|tmin|tmax|mask)\[(\d+(?:, \d+)*)\]")
_RAY = re.compile(r"^ray (\d+(?:, \d+)*):")


def _renamed(error: Exception, offsets: tuple, own: dict) -> Exception:
    """``error`` with the rows it names moved from the chunk's indices to
    the whole array's: by the chunk's offsets, right-aligned to each
    array's own leading dimensions, except where that array has size 1
    (broadcast)."""
    def shift(indices: str, name: str | None) -> str:
        values = [int(i) for i in indices.split(", ")]
        sizes = own.get(name) or (None,) * len(values)
        moved = [i + (o if size != 1 else 0)
                 for i, o, size in zip(values, offsets[-len(values):], sizes[-len(values):])]
        return ", ".join(map(str, moved))

    text = _LABEL.sub(lambda m: f"{m[1]}[{shift(m[2], m[1])}]", str(error))
    text = _RAY.sub(lambda m: f"ray {shift(m[1], None)}:", text)
    return type(error)(text)


def _call(verb, offsets: tuple, own: dict, *args, **kwargs):
    try:
        return verb(*args, **kwargs)
    except (ValueError, TypeError) as error:
        if not any(offsets):
            raise
        raise _renamed(error, offsets, own) from None


_record_pool = ResultPool()

#: Rows of a record array filled at a time: all its fields are written while
#: those rows are in cache, where a whole field at a time would stream the
#: whole array through memory once per field.
RECORD_ROWS = 1 << 14


def records(result, dtype: np.dtype) -> np.ndarray:
    """A dataclass of arrays (Hits, ClosestPoints) as one record array of
    ``dtype`` (HITS, CLOSEST), as a chunk's task returns it; lent by a pool
    (hlbvh_cl.query.results) as the queries' own results are: a chunk's
    record array is large, and fresh memory costs a page fault per page."""
    scalar = next(name for name in dtype.names if dtype[name].shape == ())
    shape = getattr(result, scalar).shape
    out = _record_pool.empty(shape, dtype)
    flat = out.reshape(-1)
    fields = [(name, getattr(result, name).reshape(len(flat), *dtype[name].shape))
              for name in dtype.names]
    for first in range(0, len(flat), RECORD_ROWS):
        rows = flat[first:first + RECORD_ROWS]
        for name, array in fields:
            rows[name] = array[first:first + RECORD_ROWS]
    return out


# ---------------------------------------------------------------- ray queries

def _ray_block(*blocks, names, own, starts, verb, limits, block_id=None):
    *blocks, shipped = blocks
    given = dict(zip(names, blocks))
    offsets = tuple(s[i] for s, i in zip(starts, block_id or ()))
    for name in ("tmin", "tmax", "mask"):
        if name in given:
            limits = dict(limits, **{name: given[name][..., 0]})
    rays = (given["rays"], None) if "rays" in given else (given["origins"], given["directions"])
    with shipped.scene() as scene:
        result = _call(getattr(scene, verb), offsets, own, *rays, **limits)
    if verb == "intersect_all":  # its hits, each with its ray's index in the whole array
        out = np.empty(len(result), HIT_LIST)
        for name in HIT_LIST.names:
            out[name] = getattr(result, name)
        out["ray_index"] += offsets[0] * int(np.prod(result.shape[1:], dtype=np.int64))
        return out
    return records(result, HITS) if verb == "intersect" else result


def _ray_inputs(origins, directions, tmin, tmax, mask):
    """The rays as dask arrays (name -> array), their leading shape, and the
    limits and mask that are one value for all; checked as the Scene
    methods check them."""
    if directions is None:
        arrays = {"rays": vectors("rays", origins, 6)}
        lead = arrays["rays"].shape[:-1]
    else:
        arrays = {"origins": vectors("origins", origins), "directions": vectors("directions",
                                                                                  directions)}
        lead = inputs.ray_shape(arrays["origins"].shape, arrays["directions"].shape)
    limits = {}
    for name, value in (("tmin", tmin), ("tmax", tmax), ("mask", mask)):
        if value is None:
            continue
        if isinstance(value, da.Array) or np.ndim(value) > 0:
            arrays[name] = _per_ray(name, value, lead)
        elif name == "mask":
            limits[name] = inputs.ray_masks(value, lead)
        else:
            limits[name] = inputs.limits(name, value, lead)
    if "tmin" in limits and "tmax" in limits:
        inputs.check_limits(limits["tmin"], limits["tmax"], lead)
    return arrays, lead, limits


def _ray_query(verb: str, dtype: np.dtype, scene, origins, directions, tmin, tmax, mask,
               client):
    client = _current_client(client)
    arrays, lead, limits = _ray_inputs(origins, directions, tmin, tmax, mask)
    return _blocks(_ray_block, arrays, ship(scene, client), dtype, len(lead), verb=verb,
                   limits=limits)


def intersect(scene: Scene, origins, directions=None, tmin=0.0, tmax=np.inf, mask=None, *,
              client=None) -> Hits:
    """Scene.intersect over chunks: a Hits whose fields are dask arrays in
    the rays' leading shape and chunks, all taken from one record array per
    chunk (fields computed together cost one traversal per chunk)."""
    records = _ray_query("intersect", HITS, scene, origins, directions, tmin, tmax, mask, client)
    return Hits(**{name: records[name] for name in HITS.names})


def occluded(scene: Scene, origins, directions=None, tmin=0.0, tmax=np.inf, mask=None, *,
             client=None) -> da.Array:
    """Scene.occluded over chunks: bool, in the rays' leading shape."""
    return _ray_query("occluded", np.dtype(bool), scene, origins, directions, tmin, tmax, mask,
                      client)


def count_intersections(scene: Scene, origins, directions=None, tmin=0.0, tmax=np.inf,
                        mask=None, *, client=None) -> da.Array:
    """Scene.count_intersections over chunks: int32, in the rays' leading shape."""
    return _ray_query("count_intersections", np.dtype(np.int32), scene, origins, directions,
                      tmin, tmax, mask, client)


def intersect_all(scene: Scene, origins, directions=None, tmin=0.0, tmax=np.inf, max_hits=None,
                  mask=None, *, client=None) -> AllHits:
    """Scene.intersect_all over chunks of rays: an AllHits of dask arrays.
    The rays are chunked along their first leading axis only (the others
    are made one chunk), so the chunks' hits, one after another, are in the
    rays' C order: ray_index and the hit fields are those of one
    intersect_all of all the rays, their chunks of unknown length until
    computed.  offsets and counts come from count_intersections (one more
    counting pass over the rays, run only if they are computed)."""
    max_hits = check_max_hits(max_hits)
    client = _current_client(client)
    arrays, lead, limits = _ray_inputs(origins, directions, tmin, tmax, mask)
    if not lead:
        raise ValueError("intersect_all over dask arrays takes rays with a leading dimension "
                         "(one ray: use Scene.intersect_all)")
    whole = len(lead) + 1  # axes of a full-rank array; only axis 0 of those stays chunked
    arrays = {name: a.rechunk({k: -1 for k in range(a.ndim) if k != a.ndim - whole})
              for name, a in arrays.items()}
    shipped = ship(scene, client)
    pairs = []
    for array in arrays.values():
        pairs += [array, tuple(range(whole - array.ndim, whole))]
    chunks, aligned = unify_chunks(*pairs)
    own = {name: a.shape[:-1] for name, a in zip(arrays, aligned)}
    first_axis = chunks[0]
    hits = da.map_blocks(_ray_block, *aligned, shipped, names=tuple(arrays), own=own,
                         starts=_starts(tuple(chunks[k] for k in range(len(lead)))),
                         verb="intersect_all", limits=dict(limits, max_hits=max_hits),
                         dtype=HIT_LIST, drop_axis=list(range(1, whole)),
                         chunks=((np.nan,) * len(first_axis),), meta=np.empty((0,), HIT_LIST))
    counts = _blocks(_ray_block, arrays, shipped, np.dtype(np.int32), len(lead),
                     verb="count_intersections", limits=limits).astype(np.int64)
    if max_hits is not None:
        counts = da.minimum(counts, max_hits)
    counts = counts.reshape(-1)
    # dask's cumsum fails to merge an empty chunk with the next; they add nothing
    filled = tuple(size for size in counts.chunks[0] if size)
    if filled and len(filled) < len(counts.chunks[0]):
        counts = counts.rechunk((filled,))
    offsets = da.concatenate([da.zeros(1, dtype=np.int64), da.cumsum(counts)])
    return AllHits(offsets=offsets, shape=tuple(lead),
                   **{name: hits[name] for name in HIT_LIST.names})


# ---------------------------------------------------------------- point queries

def _point_block(points, shipped, *, names, own, starts, verb, options, block_id=None):
    offsets = tuple(s[i] for s, i in zip(starts, block_id or ()))
    with shipped.scene() as scene:
        result = _call(getattr(scene, verb), offsets, own, points, **options)
    return records(result, CLOSEST) if verb == "closest_points" else result


def _point_query(verb: str, dtype: np.dtype, scene, points, client, **options):
    client = _current_client(client)
    array = vectors("points", points)
    return _blocks(_point_block, {"points": array}, ship(scene, client), dtype,
                   array.ndim - 1, verb=verb, options=options)


def closest_points(scene: Scene, points, max_distance=np.inf, *, client=None) -> ClosestPoints:
    """Scene.closest_points over chunks: a ClosestPoints of dask arrays, all
    taken from one record array per chunk."""
    records = _point_query("closest_points", CLOSEST, scene, points, client,
                           max_distance=check_max_distance(max_distance))
    return ClosestPoints(**{name: records[name] for name in CLOSEST.names})


def winding_number(scene: Scene, points, *, client=None) -> da.Array:
    """Scene.winding_number over chunks: float32, in the points' leading shape."""
    return _point_query("winding_number", np.dtype(np.float32), scene, points, client)


def signed_distance(scene: Scene, points, *, client=None) -> da.Array:
    """Scene.signed_distance over chunks: float32, negative inside."""
    return _point_query("signed_distance", np.dtype(np.float32), scene, points, client)


def contains(scene: Scene, points, *, client=None) -> da.Array:
    """Scene.contains over chunks: bool."""
    return _point_query("contains", np.dtype(bool), scene, points, client)


# ---------------------------------------------------------------- frames

_renderers: OrderedDict = OrderedDict()
_renderers_lock = threading.Lock()


def task_renderer(scene: Scene, look: dict) -> Renderer:
    """This process's Renderer of ``scene`` with this look (Renderer's
    colors, light, materials, emitters and instance_materials, checked), as
    render_frames' tasks use it: made once (the last RENDERERS kept), as its
    pipeline compiles kernels and allocates buffers."""
    key = (id(scene), dask.base.tokenize(look))
    with _renderers_lock:
        if key in _renderers:
            _renderers.move_to_end(key)
            return _renderers[key][1]
        renderer = Renderer(scene, **look)
        _renderers[key] = (scene, renderer)  # the scene kept: its id names it
        while len(_renderers) > RENDERERS:
            _renderers.popitem(last=False)
        return renderer


def _render_frames(shipped, cameras, paths, look, options) -> list:
    """One task: its frames rendered, each returned or written to its path."""
    out = []
    with shipped.scene() as scene:  # every frame of the task of one content
        shared = task_renderer(scene, look)
        for camera, path in zip(cameras, paths):
            image = shared.render(camera, **options)
            if path is None:
                out.append(image)
            elif path.endswith(".exr"):
                from ..io.exr import write_exr
                write_exr(path, image)
                out.append(path)
            else:
                import imageio.v3 as iio
                iio.imwrite(path, image)
                out.append(path)
    return out


#: The image formats render_frames writes: EXR holds the linear float32
#: radiance of hdr=True; the others the 8-bit images (imageio).
HDR_SUFFIXES, LDR_SUFFIXES = (".exr",), (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def _output_folder(output) -> Path:
    """render_frames' ``output`` as a folder, made where missing."""
    if not isinstance(output, (str, os.PathLike)):
        raise TypeError(f"output must be a folder's path (a str or a pathlib.Path), got "
                        f"{type(output).__name__}")
    folder = Path(output)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _frame_files(name, count: int, hdr: bool) -> list[str]:
    """The file of each of ``count`` frames in the output folder, from
    render_frames' ``name``; every error before any task renders."""
    if name is None:
        name = "frame_{:05d}" + (".exr" if hdr else ".png")
    if not isinstance(name, str):
        raise TypeError(f"name must be a file name with {{}} for the frame's index, such as "
                        f"'frame_{{:05d}}.png', got {type(name).__name__}")
    try:
        files = [name.format(k) for k in range(count)]
    except (IndexError, KeyError, ValueError) as error:
        raise ValueError(f"name {name!r} must take the frame's index as its one {{}} field "
                         f"(such as 'frame_{{:05d}}.png'): {type(error).__name__}: "
                         f"{error}") from None
    if len(set(files)) < count:
        raise ValueError(f"name {name!r} gives {count} frames one file: it needs a {{}} field "
                         f"for the frame's index, such as 'frame_{{:05d}}.png'")
    for file in files[:1]:
        if Path(file).name != file:
            raise ValueError(f"name {name!r} must be a file name in the output folder, "
                             f"without a folder of its own, got {file!r}")
        suffix = Path(file).suffix.lower()
        taken = HDR_SUFFIXES if hdr else LDR_SUFFIXES
        if suffix not in taken:
            kind = "hdr=True writes float32 radiance, to" if hdr else \
                "8-bit images (hdr=False) go to"
            raise ValueError(f"name {name!r}: {kind} {', '.join(taken)} files, not "
                             f"{suffix or 'a name without a suffix'}")
    return files


def render_frames(scene: Scene, cameras, width: int, height: int, client=None, output=None, *,
                  colors=None, light=None, shading: str = "diffuse", shadows: bool = True,
                  spp: int = 1, ao_samples: int = AO_SAMPLES, ao_distance: float | None = None,
                  materials=None, emitters=None, instance_materials=None, max_depth: int = -1,
                  rr_depth: int = RR_DEPTH, seed: int = 0, rfilter: str = "box", hdr: bool = False,
                  frames_per_task: int = 1, progress: bool = True,
                  name: str | None = None) -> list:
    """Renders each of ``cameras`` (hlbvh_cl.Camera) as a Renderer of
    ``colors``, ``light``, ``materials``, ``emitters`` and
    ``instance_materials`` would render it
    with the options given (Renderer.render's), ``frames_per_task`` frames
    a task, on ``client``'s cluster (else the default client's, else dask's
    local threads).  Returns the (height, width, 3) images in the cameras'
    order (uint8, or float32 linear with ``hdr``); with ``output``, a
    folder that the workers can write to, the workers write them there
    (``name`` formatted with the frame's index: a file name with a {}
    field, .exr with ``hdr``, else .png, .jpg, .bmp or .tif; by default
    frame_00000.png, or .exr with ``hdr``) and their paths are returned
    instead.  ``progress`` shows dask's progress bar.  Every argument is
    checked before any task renders."""
    if isinstance(cameras, Camera) or not isinstance(cameras, Sequence):
        raise TypeError(f"cameras must be a list of hlbvh_cl.Camera, got "
                        f"{type(cameras).__name__}")
    for k, camera in enumerate(cameras):
        if not isinstance(camera, Camera):
            raise TypeError(f"cameras[{k}] must be a hlbvh_cl.Camera, got "
                            f"{type(camera).__name__}")
    settings = dict(shading=shading, shadows=shadows, spp=spp, ao_samples=ao_samples,
                    ao_distance=ao_distance, max_depth=max_depth, rr_depth=rr_depth, seed=seed,
                    rfilter=rfilter)
    # the errors a local render raises, before any task (and for no camera)
    check_settings(cameras[0] if cameras else Camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0)),
                   width, height, **settings)
    for flag, value in (("hdr", hdr), ("progress", progress)):
        if not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"{flag} must be True or False, got {type(value).__name__}")
    options = dict(width=width, height=height, hdr=bool(hdr), **settings)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a hlbvh_cl.Scene, got {type(scene).__name__}")
    look = dict(colors=colors, light=light, materials=materials, emitters=emitters,
                instance_materials=instance_materials)
    Renderer(scene, **look).look()  # its errors, before any task
    frames_per_task = inputs.integer("frames_per_task", frames_per_task, 1)
    paths = [None] * len(cameras)
    if output is not None:
        folder = _output_folder(output)
        paths = [str(folder / file) for file in _frame_files(name, len(cameras), bool(hdr))]
    if not cameras:
        return []
    client = _current_client(client)
    shipped = ship(scene, client)
    groups = [slice(k, k + frames_per_task) for k in range(0, len(cameras), frames_per_task)]
    if client is not None:
        token = dask.base.tokenize(shipped.key, list(cameras), paths, look, options)
        futures = [client.submit(_render_frames, shipped, list(cameras[g]), paths[g], look,
                                 options, key=f"hlbvh_cl-frames-{token}-{k}")
                   for k, g in enumerate(groups)]
        if progress:
            from distributed import progress as show
            show(futures)
        found = client.gather(futures)
    else:
        tasks = [dask.delayed(_render_frames, pure=True)(shipped, list(cameras[g]), paths[g],
                                                         look, options)
                 for g in groups]
        if progress:
            from dask.diagnostics import ProgressBar
            with ProgressBar():
                found = dask.compute(*tasks)
        else:
            found = dask.compute(*tasks)
    frames = [frame for group in found for frame in group]
    return [Path(f) for f in frames] if output is not None else frames
