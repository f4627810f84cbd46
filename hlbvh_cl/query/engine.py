"""The one launch engine of the queries: rays, all hits and points alike.

A query hands the engine a batch of items (rays or points): their input
arrays, a row per item; the values each launch takes either as one number
or a row per item (a ray's tmin, tmax and mask: "stepped"); the output
arrays, a row per item, or a segment of rows per item (intersect_all's
hits); and optionally an order to run the items in.  The query's own
``launch(n, Launch)`` enqueues its kernel with the buffers the engine gives
it.  The engine does the rest, the same way for every query:

- **Chunking and pacing.**  Launches take at most ``most`` items, the first
  FIRST_LAUNCH (the query's), each later one as many as the last to end
  says fit in LAUNCH_SECONDS (LaunchSizes), so that Ctrl-C, which waits for
  the launches in flight, is answered within a second whatever a ray costs;
  at most two are in flight.  A batch with a ``key`` (its kernel's name)
  starts where the last batch of that key ended: a scene whose items cost
  much (a crowd of overlapping instances) pays the query's first launch
  once, not per call.
- **Zero copy or copy.**  On PoCL's CPU device the kernels use the numpy
  arrays themselves (CL_MEM_USE_HOST_PTR, zero_copy); elsewhere the inputs
  go up into device buffers reused between launches, and the results come
  back from others, or are written in place where the runtime can use the
  arrays there (Intel's, for arrays that start on a page: outputs_in_place).
- **Staging** (on request: a query's ``staging``; see ``staging`` for why
  not by default, GPUs included).  Each run's
  rows are taken straight into pinned host memory (Staging: buffers made
  with CL_MEM_ALLOC_HOST_PTR and mapped once, the way NVIDIA's OpenCL
  gives pinned memory) and copied up on a queue of their own, the results
  copied down into pinned memory on another, both chunked by the runs: two
  runs alternate between two sets of these buffers, so that one run's
  copies overlap the other's kernel.  The host waits for a run's results
  only to put them into the result arrays (the pacing's wait); the buffers
  are reused between calls.
- **Whole arrays by slots** (``whole``, CPU devices): every launch reads and
  writes the whole arrays in place, the items of a run of ``order`` given
  as slots, so that nothing is gathered or scattered on the host.
  Otherwise an ordered batch's rows are taken on the host per launch and
  its results put back once the launch ends.
- **Collection and the overflow check.**  Results are mapped (in place) or
  copied back; the counters (int32 [0]: a walk ran out of stack; [1]: the
  query's own; [2] and [3]: the input checks of arrays already on the
  device, query/on_device.py) are read once, at the end, the only blocking
  wait.
- **Arrays on the device.**  A batch's inputs and outputs may be pyopencl
  arrays of the engine's context (query/on_device.py): the kernels use
  their buffers as they are, each launch a range of the whole arrays at a
  global work offset (Batch.slots False), and nothing of theirs crosses to
  the host.  A batch's ``then`` enqueues more work on its results before
  that one wait, with reads of its own that the wait covers (intersect_all
  on the device: its segments' scan, and the read of the hits' total).

On any error or Ctrl-C the queues are finished before the exception leaves:
the launches and copies in flight may still write the caller's arrays and
the reused buffers.
"""
from __future__ import annotations

import itertools
import math
import threading
from dataclasses import dataclass, field

import numpy as np
import pyopencl as cl

from ..build.instances import InstancedTree
from ..core import layout
from ..core.tree import Tree, leaf_defines
from ..device.runtime import Runtime
from .results import starts_on_page

#: A batch's first launch takes at most this many items (rays; point queries
#: start lower), and each later one what the last to end says fits in
#: LAUNCH_SECONDS: a scene of many overlapping instances makes an item cost
#: far more.
FIRST_LAUNCH = 1 << 16
LAUNCH_SECONDS = 0.25

#: int32 counters a batch clears and reads back (the module's docstring).
COUNTERS = 4

#: Launches in flight at most, and so the sets of buffers the staging path
#: alternates between (Staging).
IN_FLIGHT = 2

#: Stack sizes are rounded up to a multiple of this so that few program
#: variants get compiled.
STACK_GRANULE = 16


def zero_copy(rt: Runtime) -> bool:
    """Whether queries hand the kernels the numpy arrays themselves
    (CL_MEM_USE_HOST_PTR) instead of device copies.

    Only on PoCL's CPU device, where a device copy is just two memcpys and
    zero copy measured faster.  Intel's CPU runtime measured the other way,
    and a GPU's memory is its own.
    """
    return (not rt.profile.gpu and rt.device.id.startswith("pocl")
            and bool(rt.device.cl_device.host_unified_memory))


def staging(rt: Runtime) -> bool:
    """Whether, off zero copy, the rows and results travel by default
    through pinned staging buffers, with their copies on queues of their
    own (Staging), rather than through plain device buffers.

    Never by default.  The path was built for GPUs, where only a copy from
    pinned memory runs by DMA while the host goes on; but on the one GPU
    measured (an NVIDIA H200: three runs of bench.gpu and an interleaved
    sweep of launch sizes) plain device buffers were faster, for 3M camera rays
    and for a 1K-ray call alike.  Its driver stages a copy from pageable
    memory through pinned memory of its own and pipelines it, while this
    path adds a memcpy on the host that overlaps only with other launches.
    A query's ``staging`` attribute turns it on (bench.gpu measures both).
    HLBVH_CL_PROFILE=gpu does not change this; CPU devices keep zero copy
    (PoCL) and device buffers with results in place (Intel's).
    """
    return False


def outputs_in_place(rt: Runtime) -> bool:
    """Whether, off zero copy, the kernels write results straight into the
    result arrays where these start on a page (results.ALIGNMENT; Intel's
    CPU runtime uses a host pointer in place only there).

    On Intel's CPU runtime, where the inputs measured slower in place (a
    caller's arrays seldom start on a page) but the results written in
    place measured faster, with the same results.
    """
    return rt.device.id.startswith("intel") and not rt.profile.gpu


def work_group_size(rt: Runtime) -> int:
    """Work-items per group for the traversal kernels.

    1 on CPUs.  PoCL runs a group as a loop over its work-items and keeps
    each item's private arrays (the walks' rays, stacks and states) in
    per-item copies that every access indexes by the item's number; a group
    of one addresses them directly (the compiled walk showed the indexing on
    every step).  Against groups of 8 (4 where a work-item takes two lane
    groups), which had measured faster than 16 and 64, groups of one traced
    faster on PoCL, closest and shadow rays, and within noise on Intel's CPU
    runtime (figures in the commit that set this).  The traversal kernels
    hold no local memory and no barrier, so the size changes only speed.
    GPUs want at least a warp/wavefront.
    """
    size = 64 if rt.profile.gpu else 1
    return min(size, rt.device.cl_device.max_work_group_size)


def stack_size(tree) -> int:
    """A stack that cannot overflow: a wide node pushes at most WIDE_ARITY - 1
    children, and only those of the nodes on the path to the current one stay
    on the stack.  Sized from the tree's depth, so that a tree whose depth is
    wrong overflows (and raises) instead of being trusted in part."""
    depth = (layout.WIDE_ARITY - 1) * max(1, int(tree.depth))
    return (depth + STACK_GRANULE - 1) // STACK_GRANULE * STACK_GRANULE


def kernel_defines(rt: Runtime, tree, variant, packet: int, **extra) -> dict:
    """The defines every query kernel is built with for ``tree``: its stack,
    the items per work-item, the kernel variant's and the device's (CPU
    prefetch), INSTANCES for a two-level scene, INTERLEAVED_WALKS where a
    CPU work-item walks its rays together (interleaved_walks), SPHERES for a
    flat tree with spheres, the leaf layout's, LEAF_QUADS where a ray tests a
    leaf's triangles four at a time (leaf_quads), then the query's own."""
    defines = {"STACK_SIZE": stack_size(tree), "PACKET_SIZE": packet, **variant.defines,
               **rt.prefetch_defines}
    if isinstance(tree, InstancedTree):
        defines["INSTANCES"] = 1
    elif interleaved_walks(rt, tree, defines["STACK_SIZE"], packet):
        defines["INTERLEAVED_WALKS"] = 1
    if getattr(tree, "spheres", None) is not None:
        defines["SPHERES"] = 1
    indexed = getattr(tree, "indexed", False)
    defines.update(leaf_defines(indexed))
    if leaf_quads(rt):
        defines["LEAF_QUADS"] = 1
    return {**defines, **extra}


#: Private bytes a work-item's interleaved walks may take for their stacks
#: (query/walk/walk.h's walks: WALK_LANES stacks of STACK_SIZE + 1 items of
#: 12 bytes, a work-item's rays: rays.py's lane_groups); a deeper tree walks
#: its rays one after the other.
INTERLEAVED_STACK_BYTES = 32 * 1024

#: Trees whose nodes and triangles take less than this stay mostly in a
#: core's caches: their walks seldom wait on memory, and interleaving them
#: only costs.  Measured on parts of the bunny's triangles (trees of 0.5 to
#: 5.5 MiB, random rays): a loss up to 1.7 MiB on PoCL, even near 2.8 MiB,
#: a gain from there on both runtimes; the Cornell box's tree (0.55 MiB)
#: path-traced slower interleaved (figures in the commit that set this).
INTERLEAVED_MIN_TREE_BYTES = 2 * 1024 * 1024


def leaf_quads(rt: Runtime) -> bool:
    """Whether a single ray's walk tests a leaf's triangles four at a time,
    one vector lane each (kernels/query/rays/quad.h): on CPUs, where the
    edge test of four costs little more than that of one, and a ray leaving
    a surface tests most of its triangles in the leaves around its origin.
    Either leaf layout: a compact tree's (Scene(..., compact=True)) lanes
    take their corners through its indices.  A GPU's lanes are its rays
    already."""
    return not rt.profile.gpu


def interleaved_walks(rt: Runtime, tree, stack: int, packet: int) -> bool:
    """Whether a work-item's rays that do not go as one packet walk
    interleaved, a step of each in turn (query/walk/walk.h's walks), rather
    than one after the other: on CPUs, where one ray's walk stalls on each
    cache miss and the others' steps fill the stalls (measured faster on
    incoherent rays on PoCL and Intel's runtime), while a GPU hides the
    misses with other work-items; for trees larger than a core's cache
    (INTERLEAVED_MIN_TREE_BYTES) whose stacks fit INTERLEAVED_STACK_BYTES."""
    return (not rt.profile.gpu and packet > 1
            and sum(tree.memory().values()) >= INTERLEAVED_MIN_TREE_BYTES
            and packet * (stack + 1) * 12 <= INTERLEAVED_STACK_BYTES)


def refuse_spheres(tree, query: str) -> None:
    """A ValueError for a query that does not see a tree's analytic spheres
    (only closest and any hit test them: kernels/query/rays/sphere.h), rather
    than an answer that leaves them out."""
    if getattr(tree, "spheres", None) is not None:
        first = tree.sphere_geom
        raise ValueError(f"{query} takes triangle meshes only, and this scene has "
                         f"{tree.sphere_count} analytic sphere(s) (geom_id {first} to "
                         f"{first + tree.sphere_count - 1}): only intersect and occluded see "
                         "spheres; give them as meshes (trimesh.creation.icosphere) for this query")


def check_tree(rt: Runtime, tree) -> bool:
    """Validates a tree for a query on ``rt``; False when it holds no
    triangle (every query misses)."""
    if not isinstance(tree, (Tree, InstancedTree)):
        raise TypeError(f"tree must be a hlbvh_cl.core.tree.Tree, got {type(tree).__name__}")
    if tree.released:
        raise ValueError("this Tree was released when its Scene rebuilt")
    if tree.triangle_count == 0:
        return False
    if tree.nodes.context != rt.context:
        raise ValueError(f"tree lives on another OpenCL context than this query "
                         f"({rt.device.id}); build it with the same runtime")
    if tree.depth < 1 or tree.node_count < 1:
        raise ValueError(f"tree is malformed: depth={tree.depth}, node_count={tree.node_count}")
    return True


def collect(queue: cl.CommandQueue, buffer: cl.Buffer, array: np.ndarray,
            in_place: bool) -> cl.Event:
    """Enqueues what brings a launch's results from ``buffer`` into ``array``:
    where the kernel wrote the array itself (a USE_HOST_PTR buffer over it),
    a map of the buffer, which makes them visible without a copy; else a
    copy back.  The caller keeps the event: pyopencl's events of non-blocking
    copies wait when they are dropped."""
    if in_place:
        mapped, event = cl.enqueue_map_buffer(queue, buffer, cl.map_flags.READ, 0, array.shape,
                                              array.dtype, is_blocking=False)
        mapped.base.release(queue)
        return event
    return cl.enqueue_copy(queue, array, buffer, is_blocking=False)


def take_rows(array: np.ndarray, order: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """array[order], a 2-D array's rows gathered as one item each (numpy's
    fancy indexing of an (N, 3) array goes element by element); into
    ``out`` (contiguous) where given."""
    if array.ndim == 1:
        return np.take(array, order, out=out)
    item = np.dtype((np.void, array.itemsize * array.shape[1]))
    rows = np.ascontiguousarray(array).view(item).reshape(-1)
    if out is not None:
        np.take(rows, order, out=out.view(item).reshape(-1))
        return out
    return np.take(rows, order).view(array.dtype).reshape(-1, array.shape[1])


def put_rows(out: np.ndarray, order: np.ndarray, values: np.ndarray) -> None:
    """out[order] = values, as take_rows's inverse."""
    if out.ndim == 2:
        item = np.dtype((np.void, out.itemsize * out.shape[1]))
        out = out.view(item).reshape(-1)
        values = np.ascontiguousarray(values).view(item).reshape(-1)
    out[order] = values


def engine_setting(name: str, doc: str) -> property:
    """A query's property that reads and sets its engine's ``name`` (the
    engine owns the launch settings; the query shows them)."""
    return property(lambda query: getattr(query.engine, name),
                    lambda query, value: setattr(query.engine, name, value), doc=doc)


class LaunchSizes:
    """Items per launch for a batch: ``first`` for the first launch, then
    what the last one ended took per item allows in LAUNCH_SECONDS, always
    within [1, most]."""

    def __init__(self, most: int, first: int | None = None):
        self.most = most
        self.size = max(1, min(most, FIRST_LAUNCH if first is None else first))
        #: whether ``size`` comes from a launch that ended (this batch's, or
        #: the last batch's of its key: Engine.paced)
        self.measured = False

    def ended(self, event, items: int) -> None:
        """A launch of ``items`` items has ended (its profiled event)."""
        seconds = (event.profile.end - event.profile.start) * 1e-9
        fits = LAUNCH_SECONDS * items / seconds if seconds > 0 else self.most
        self.size = int(max(1, min(self.most, fits)))
        self.measured = True


@dataclass
class Launch:
    """What the engine gives one launch of a query's kernel."""

    count: int  # items in this launch
    #: each input and output array's buffer, by name: its rows for this
    #: launch, or the whole array (Batch.whole)
    buffers: dict
    #: each stepped value's (buffer, step): step 1, a row per item; 0, one value
    steps: dict
    slots: cl.Buffer     # whole arrays: this launch's items (uint32 slots); else a stand-in
    indexed: np.uint32   # 1 where ``slots`` are read
    #: whole arrays without slots (Batch.slots False): the launch's items
    #: are [first, first + count) of the arrays; else 0
    #: segmented outputs: (the items' offsets, the first output row, the
    #: first item) as the buffers hold them; else ()
    segments: tuple = ()
    first: int = 0


@dataclass
class Batch:
    """A query's items for the engine (see the module's docstring)."""

    count: int
    inputs: dict                      # name -> array, a row per item
    outputs: dict                     # name -> array, a row per item (or per segment row)
    stepped: dict = field(default_factory=dict)  # name -> 0-d value or a row per item
    order: np.ndarray | None = None   # uint32: run the items in this order
    whole: bool = False               # whole arrays in place, items by slots
    #: int64 (count + 1,): item i's output rows (a pyopencl array: whole
    #: arrays, runs by items alone)
    segments: object = None
    max_rows: int | None = None       # segmented: output rows per launch at most
    most: int | None = None           # items per launch at most (None: the engine's)
    first: int | None = None          # items in the first launch (None: FIRST_LAUNCH)
    #: enqueues the checks of inputs already on the device, after the
    #: counters are cleared: check(buffers, steps), as a Launch has them
    check: object = None
    #: whole arrays: False where the kernel takes its items as a range
    #: [Launch.first, + count) (a global offset) instead of by slots, which
    #: then need not go up to the device
    slots: bool = True
    #: items per launch are a multiple of this, but for the last
    granule: int = 1
    #: the batches of one key (the kernel's name) size their first launch
    #: as the last one's ended (Engine.paced)
    key: str | None = None
    #: enqueues work after the last launch, before the counters are read:
    #: then() -> the events of its reads into host arrays, which the
    #: call's one wait covers too (intersect_all on the device: the scan of
    #: its counts, and the read of their total)
    then: object = None


class Staging:
    """The staging path's memory and queues (``staging``): IN_FLIGHT sets of
    pinned host buffers and of device buffers, by name, grow-only and reused
    between calls, and two queues for the copies, ``up`` (host to device)
    and ``down``.  Off the kernels' queue, a run's copies wait for their own
    kernel only (events), not for everything enqueued before them; one queue
    per direction, as a GPU has a copy engine per direction, so that one
    run's results go down while the next run's rows go up.

    Pinned memory is a buffer made with CL_MEM_ALLOC_HOST_PTR and mapped
    once, for good; its mapping is the host side of the copies (NVIDIA's
    OpenCL Best Practices Guide, "Pinned Memory")."""

    def __init__(self, rt: Runtime):
        self.rt = rt
        self.up = cl.CommandQueue(rt.context, rt.device.cl_device)
        self.down = cl.CommandQueue(rt.context, rt.device.cl_device)
        #: per set: name -> (pinned buffer, its mapping as uint8)
        self.pinned: list[dict] = [{} for _ in range(IN_FLIGHT)]
        #: per set: name -> device buffer
        self.device: list[dict] = [{} for _ in range(IN_FLIGHT)]

    def reserve(self, sizes: dict[str, int]) -> None:
        """Every set with at least ``sizes`` bytes by name, pinned and on
        the device (the maps of new pinned buffers wait, once each)."""
        context, flags = self.rt.context, cl.mem_flags
        for pinned, device in zip(self.pinned, self.device):
            short = {name: max(4, size) for name, size in sizes.items()
                     if name not in device or device[name].size < size}
            if not short:
                continue
            for name in short:  # release the old ones before allocating
                device.pop(name, None)
                old = pinned.pop(name, None)
                if old is not None:
                    old[1].base.release(self.up)
            self.rt.check_allocation("query staging buffers", short)
            for name, size in short.items():
                device[name] = cl.Buffer(context, flags.READ_WRITE, size)
                buffer = cl.Buffer(context, flags.READ_WRITE | flags.ALLOC_HOST_PTR, size)
                mapped, _ = cl.enqueue_map_buffer(self.up, buffer,
                                                  cl.map_flags.READ | cl.map_flags.WRITE, 0,
                                                  (size,), np.uint8, is_blocking=True)
                pinned[name] = (buffer, mapped)

    def host(self, slot: int, name: str, like: np.ndarray, rows: int) -> np.ndarray:
        """``rows`` rows shaped as ``like``'s in set ``slot``'s pinned ``name``."""
        shape = (rows, *like.shape[1:])
        nbytes = math.prod(shape) * like.itemsize
        return self.pinned[slot][name][1][:nbytes].view(like.dtype).reshape(shape)

    def finish(self) -> None:
        self.up.finish()
        self.down.finish()


class Engine:
    """Runs a query's batches (``run``) on one runtime, with the buffers it
    reuses between launches: one batch at a time."""

    def __init__(self, rt: Runtime, most: int):
        self.rt = rt
        self.most = most  # items per launch at most
        #: whether the kernels read the inputs and write the results in the
        #: numpy arrays themselves (zero_copy); else the inputs go up and the
        #: results come back through device buffers reused between launches
        self.zero_copy = zero_copy(rt)
        #: without zero_copy: whether results that start on a page are
        #: written in place (outputs_in_place)
        self.outputs_in_place = not self.zero_copy and outputs_in_place(rt)
        #: without zero_copy: whether rows and results travel through pinned
        #: staging buffers (staging; made on first use: self.stage)
        self.staging = not self.zero_copy and staging(rt)
        self.stage: Staging | None = None
        self.counters = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * COUNTERS)
        self.unused = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY, 4)  # a stand-in argument
        self._scalars: dict[str, cl.Buffer] = {}
        self._scalar_values: dict[str, bytes] = {}  # what each of them holds
        #: the device buffers reused between launches and batches, by name
        #: (grow-only: reserve)
        self.reused: dict[str, cl.Buffer] = {}
        self._lock = threading.Lock()
        #: device time of the last batch's kernels, milliseconds
        self.last_kernel_ms = 0.0
        #: by Batch.key: the launch size the last batch of that key ended on
        self.paced: dict[str, int] = {}

    def run(self, batch: Batch, launch) -> np.ndarray:
        """Runs ``launch(n, Launch)`` over the batch; returns the counters
        (int32 [COUNTERS]) after raising RuntimeError if a walk ran out of stack."""
        with self._lock:
            try:
                return self._run(batch, launch)
            except BaseException:
                # Ctrl-C, or an error: the launches in flight (at most two)
                # may still write into the caller's arrays (zero copy) and the
                # reused buffers; let them end before anyone reuses those.
                self.rt.queue.finish()
                if self.stage is not None:
                    self.stage.finish()
                raise

    def reserve(self, sizes: dict[str, int]) -> dict[str, cl.Buffer]:
        """Grow-only device buffers of at least ``sizes`` bytes, by name,
        reused between launches and batches (the queue runs in order, so
        the next launch's copies follow the last one's reads)."""
        short = {name: size for name, size in sizes.items()
                 if name not in self.reused or self.reused[name].size < size}
        if short:
            for name in short:  # release the old ones before allocating
                self.reused.pop(name, None)
            self.rt.check_allocation("query buffers", short)
            self.reused.update({name: cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE,
                                                 max(4, size)) for name, size in short.items()})
        return {name: self.reused[name] for name in sizes}

    # -- internals -----------------------------------------------------------

    def _wrap(self, array: np.ndarray, access) -> cl.Buffer:
        """A buffer over the array's own memory (CL_MEM_USE_HOST_PTR)."""
        return cl.Buffer(self.rt.context, access | cl.mem_flags.USE_HOST_PTR, hostbuf=array)

    def _scalar(self, name: str, value: np.ndarray, uploads: list) -> cl.Buffer:
        """The buffer of the stepped value ``name`` given once for every item,
        its upload enqueued where the buffer does not hold the value already
        (its event added to ``uploads``, which the caller keeps until the
        call's one wait: a dropped pyopencl copy event waits)."""
        buffer = self._scalars.get(name)
        if buffer is None:
            buffer = self._scalars[name] = cl.Buffer(self.rt.context, cl.mem_flags.READ_ONLY, 4)
        given = np.full(1, value, value.dtype)
        # the value the buffer holds already (or will, the queue being in
        # order) is not sent again: a small call's copies cost more than
        # its kernel on a GPU
        if self._scalar_values.get(name) != given.tobytes():
            self._scalar_values.pop(name, None)  # unknown until the copy is enqueued
            uploads.append(cl.enqueue_copy(self.rt.queue, buffer, given, is_blocking=False))
            self._scalar_values[name] = given.tobytes()
        return buffer

    def _run(self, batch: Batch, launch) -> np.ndarray:
        """The batch's launches; the host waits once, for the results (and
        between launches of a batch that takes several, to size them),
        issue 57: a call's fixed cost is its host synchronisations."""
        rt, queue = self.rt, self.rt.queue
        uploads = [cl.enqueue_fill_buffer(queue, self.counters, np.int32(0), 0, 4 * COUNTERS)]
        scalars = {name: self._scalar(name, value, uploads)
                   for name, value in batch.stepped.items() if value.ndim == 0}
        rows = {**batch.inputs, **{name: value for name, value in batch.stepped.items()
                                   if value.ndim}}
        staged = not batch.whole and self.staging and not self.zero_copy
        cut, results = (self._whole if batch.whole else self._staged if staged else
                        self._chunk)(batch, rows, scalars)
        # launches in flight: (events, what ends them, the objects they use, items)
        flight: list[tuple[list, object, object, int]] = []
        events = []
        sizes = LaunchSizes(batch.most or self.most, self.paced.get(batch.key, batch.first))
        # staged and paced by the last batch of its key: two launches may be
        # in flight from the first, so that the second's copies overlap the
        # first's kernel (elsewhere nothing would overlap: one queue)
        sizes.measured = staged and batch.key in self.paced

        def retire(keep: int) -> None:
            while len(flight) > keep:
                waited, put_back, _, items = flight.pop(0)
                rt.wait(waited)
                sizes.ended(waited[0], items)
                put_back()

        for start, stop in _runs(batch, sizes):
            arguments, done, put_back, held = cut(start, stop)
            events.append(launch(stop - start, arguments))
            flight.append(([events[-1], *done(events[-1])], put_back, held, stop - start))
            # before the next run is cut: at most one left in flight, none
            # until the first has ended and sized the runs after it (the
            # last run waits with the results, below)
            if stop < batch.count:
                retire(1 if sizes.measured else 0)
        finish = [collect(queue, buffer, array, True) for buffer, array in results]
        if batch.then is not None:
            finish += batch.then()
        counters = np.zeros(COUNTERS, np.int32)
        finish.append(cl.enqueue_copy(queue, counters, self.counters, is_blocking=False))
        rt.wait([*uploads, *(event for waited, *_ in flight for event in waited), *finish])
        for waited, put_back, _, items in flight:
            sizes.ended(waited[0], items)
            put_back()
        flight.clear()
        if batch.key is not None:
            self.paced[batch.key] = sizes.size
        self.last_kernel_ms = sum((e.profile.end - e.profile.start) * 1e-6 for e in events)
        if counters[0]:
            raise RuntimeError("a query's walk overflowed its stack (sized from Tree.depth): "
                               "the tree is deeper than its depth field says")
        return counters

    def _whole(self, batch: Batch, rows: dict, scalars: dict):
        """Launches over the whole arrays in place, by slots (Batch.whole):
        numpy arrays wrapped, pyopencl arrays by their own buffers."""
        flags = cl.mem_flags
        read = {name: self._whole_buffer(array, flags.READ_ONLY) for name, array in rows.items()}
        # read too: a segmented kernel sorts the rows it wrote
        written = {name: self._whole_buffer(array, flags.READ_WRITE)
                   for name, array in batch.outputs.items()}
        buffers = {**read, **written}
        steps = {name: (read[name], np.uint32(1)) if name in read else
                 (scalars[name], np.uint32(0)) for name in batch.stepped}
        segments = () if batch.segments is None else \
            (self._whole_buffer(batch.segments, flags.READ_ONLY), np.int64(0), np.int64(0))
        order = batch.order if batch.order is not None or not batch.slots else \
            np.arange(batch.count, dtype=np.uint32)
        if batch.check is not None:
            batch.check(buffers, steps)

        def cut(start: int, stop: int):
            if not batch.slots:
                return (Launch(stop - start, buffers, steps, self.unused, np.uint32(0), segments,
                               start), _no_copies, _nothing, None)
            slots = self._wrap(order[start:stop], flags.READ_ONLY)
            arguments = Launch(stop - start, buffers, steps, slots, np.uint32(1), segments)
            return arguments, _no_copies, _nothing, slots
        # the results are mapped once, after the last launch (those on the
        # device stay there)
        return cut, [(written[name], array) for name, array in batch.outputs.items()
                     if isinstance(array, np.ndarray)]

    def _whole_buffer(self, array, access) -> cl.Buffer:
        """The buffer a whole-array launch uses for ``array``: a numpy
        array's own memory (_wrap), a pyopencl array's buffer."""
        if isinstance(array, np.ndarray):
            return self._wrap(array, access)
        if array.context != self.rt.context:
            raise ValueError("a pyopencl array of another OpenCL context than this scene's "
                             f"({self.rt.device.id}) reached the launch engine")
        return array.data

    def _chunk(self, batch: Batch, rows: dict, scalars: dict):
        """Launches over each run's rows (taken on the host in ``order``),
        in place on zero copy, else through reused device buffers (reserved
        at once for the largest run)."""
        queue, flags = self.rt.queue, cl.mem_flags
        order, segments = batch.order, batch.segments
        if not self.zero_copy:
            self.reserve(_run_bytes(batch, rows, self.most))

        def cut(start: int, stop: int):
            items = slice(start, stop) if order is None else order[start:stop]
            first, last = (start, stop) if segments is None else \
                (int(segments[start]), int(segments[stop]))
            inputs = {name: array[items] if order is None else take_rows(array, items)
                      for name, array in rows.items()}
            if segments is not None:
                inputs["segments"] = segments[start:stop + 1]
            # the results of an ordered run land in rows of their own first
            outputs = {name: array[first:last] if order is None else
                       np.empty((last - first, *array.shape[1:]), array.dtype)
                       for name, array in batch.outputs.items()}
            transfers = []
            if self.zero_copy:
                buffers = {name: self._wrap(array, flags.READ_ONLY) for name, array in inputs.items()}
            else:
                buffers = self.reserve({name: array.nbytes for name, array in inputs.items()})
                transfers += [cl.enqueue_copy(queue, buffers[name], array, is_blocking=False)
                              for name, array in inputs.items() if array.nbytes]
            in_place = self.zero_copy or (self.outputs_in_place and starts_on_page(
                *outputs.values()))
            if in_place:
                buffers.update({name: self._wrap(array, flags.WRITE_ONLY)
                                for name, array in outputs.items()})
            else:
                buffers.update(self.reserve({name: array.nbytes for name, array in outputs.items()}))
            steps = {name: (buffers[name], np.uint32(1)) if name in buffers else
                     (scalars[name], np.uint32(0)) for name in batch.stepped}
            segment = () if segments is None else \
                (buffers.pop("segments"), np.int64(first), np.int64(start))
            arguments = Launch(stop - start, buffers, steps, self.unused, np.uint32(0), segment)

            def done(_):
                return [collect(queue, buffers[name], array, in_place)
                        for name, array in outputs.items()]

            def put_back():
                if order is not None:
                    for name, array in outputs.items():
                        put_rows(batch.outputs[name], items, array)
            return arguments, done, put_back, (inputs, outputs, buffers, transfers)
        return cut, []

    def _staged(self, batch: Batch, rows: dict, scalars: dict):
        """Launches over each run's rows through the pinned staging buffers
        (Staging, reserved at once for the largest run), the runs taking
        the sets in turn: the rows are taken (in ``order``) straight into
        pinned memory and go up on their own queue, the kernel waits for
        them (a barrier on its queue), the results go down into pinned
        memory after the kernel and are put into the result arrays once
        the run has ended.  A batch of one run copies on the kernels'
        queue."""
        queue = self.rt.queue
        order, segments = batch.order, batch.segments
        if self.stage is None:
            self.stage = Staging(self.rt)
        stage = self.stage
        sizes = _run_bytes(batch, rows, self.most)
        if segments is not None:
            sizes["segments"] = segments.itemsize * (_largest_run(batch, self.most) + 1)
        stage.reserve(sizes)
        turns = itertools.count()
        given = dict(rows) if segments is None else {**rows, "segments": segments}

        def cut(start: int, stop: int):
            slot = next(turns) % IN_FLIGHT
            device = stage.device[slot]
            items = slice(start, stop) if order is None else order[start:stop]
            first, last = (start, stop) if segments is None else \
                (int(segments[start]), int(segments[stop]))
            # a batch of one run has no other kernel to overlap: its copies
            # go in order on the kernels' queue, with no event between queues
            up, down = (queue, queue) if start == 0 and stop == batch.count else \
                (stage.up, stage.down)
            uploads = []
            for name, array in given.items():
                ends = stop + 1 if name == "segments" else stop
                pinned = stage.host(slot, name, array, ends - start)
                if order is None or name == "segments":
                    pinned[...] = array[start:ends]
                else:
                    take_rows(array, items, out=pinned)
                if pinned.nbytes:
                    uploads.append(cl.enqueue_copy(up, device[name], pinned, is_blocking=False))
            if uploads and up is not queue:
                # a queue waiting on another's commands needs them flushed
                # (the OpenCL spec, clFlush): a blocking wait flushes only its own
                up.flush()
                cl.enqueue_barrier(queue, wait_for=uploads)
            buffers = {name: device[name] for name in (*rows, *batch.outputs)}
            steps = {name: (buffers[name], np.uint32(1)) if name in buffers else
                     (scalars[name], np.uint32(0)) for name in batch.stepped}
            segment = () if segments is None else \
                (device["segments"], np.int64(first), np.int64(start))
            arguments = Launch(stop - start, buffers, steps, self.unused, np.uint32(0), segment)
            results = {name: stage.host(slot, name, array, last - first)
                       for name, array in batch.outputs.items()}

            def done(kernel: cl.Event):
                if down is not queue:
                    queue.flush()  # the copies down wait on its kernel (as above)
                return [cl.enqueue_copy(down, pinned, device[name], wait_for=[kernel],
                                        is_blocking=False)
                        for name, pinned in results.items() if pinned.nbytes]

            def put_back():
                for name, pinned in results.items():
                    if order is None:
                        batch.outputs[name][first:last] = pinned
                    else:
                        put_rows(batch.outputs[name], items, pinned)
            # the uploads' events are kept until the run ends (pyopencl's
            # events of copies from host memory wait when dropped)
            return arguments, done, put_back, uploads
        return cut, []


def _nothing() -> None:
    pass


def _no_copies(_) -> list:
    return []


def _largest_run(batch: Batch, most: int) -> int:
    """The most items a run of the batch takes (_runs): its launches' limit,
    but a whole granule at least (a limit below the rays a work-item takes
    still launches one work-item's), and no more than the batch."""
    return min(batch.count, max(batch.granule, batch.most or most))


def _run_bytes(batch: Batch, rows: dict, most: int) -> dict[str, int]:
    """The bytes of each input and output of the batch's largest run."""
    most = _largest_run(batch, most)
    segments = batch.segments
    slots = most if segments is None else \
        max(batch.max_rows or 0, int(np.diff(segments).max(initial=0)))
    return {**{name: _row_bytes(array) * most for name, array in rows.items()},
            **{name: _row_bytes(array) * min(slots, len(array))
               for name, array in batch.outputs.items()}}


def _row_bytes(array: np.ndarray) -> int:
    return array.itemsize * math.prod(array.shape[1:])


def _runs(batch: Batch, sizes: LaunchSizes):
    """(start, stop) runs of the batch's items: at most sizes.size items (as
    it stands when each run is cut, rounded down to the batch's granule) and, for segmented outputs, at most
    max_rows rows unless one item alone has more; runs with no rows are
    skipped."""
    start, count = 0, batch.count
    # offsets on the device are not read: their runs are by items alone
    offsets = batch.segments if isinstance(batch.segments, np.ndarray) else None
    while start < count:
        stop = min(start + max(batch.granule, sizes.size // batch.granule * batch.granule),
                   count)
        if offsets is not None:
            if batch.max_rows is not None:
                bound = int(np.searchsorted(offsets, offsets[start] + batch.max_rows,
                                            "right")) - 1
                stop = min(stop, max(bound, start + 1))
            if offsets[stop] == offsets[start]:
                start = stop
                continue
        yield start, stop
        start = stop
