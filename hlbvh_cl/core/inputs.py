"""The shapes every query accepts, checked once, before any kernel runs.

Rays come as ``origins`` and ``directions`` of shape (..., 3) whose leading
dimensions broadcast together as numpy's do: one origin (3,) for a sensor's
many directions (LiDAR), an image's (H, W, 3) rays, or plain (R, 3) rows.
Or packed as Open3D's RaycastingScene takes them: one (..., 6) array of
origin then direction, with ``directions`` left out.  ``tmin`` and ``tmax``
are scalars or arrays that broadcast to the rays' leading shape.  Points for
the point queries are (..., 3).  Any numeric array-like is taken (lists,
float64, non-contiguous, read-only): the kernels get C-contiguous float32
rows, and the results come back in the leading shape.

A bad value is named by its index in the array the caller gave, with the
reason (not finite, overflows float32, a direction too short to invert).
"""
from __future__ import annotations

import dataclasses
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

#: Rows per block of the value checks: a block's temporaries stay in cache
#: and are reused, where whole-batch temporaries would cost a page fault per
#: 4 KiB on every call.
CHECK_BLOCK = 1 << 16

#: The mask of a ray (or an instance) that gives none: every bit, so it
#: sees (is seen by) everything.
ALL_BITS = 0xFFFFFFFF

#: The most rays, or points, one call takes: the kernels address them by
#: uint32 slots and counts.
MAX_BATCH = 2**32 - 1

#: float32's smallest normal: a direction needs a component at least this
#: large, or its inverse overflows.
_TINY = np.finfo(np.float32).tiny

#: Directions whose components all reach this magnitude are short only for
#: origins beyond 2^100 or so (Rays.shortest_direction): no row is looked at.
_SHORT = 2.0**-20


@dataclass
class Rays:
    """Checked rays: (R, 3) float32 C-contiguous rows, limits as float32
    scalars (0-d) or (R,), and the leading shape the results take."""

    origins: np.ndarray
    directions: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    shape: tuple
    origin_source: "_Vectors | None" = None
    direction_source: "_Vectors | None" = None
    #: the largest magnitude of an origin's component, and a lower bound on
    #: every direction's largest component magnitude: together they bound
    #: the t of any hit in a scene of bounded size (query.into_frame)
    farthest_origin: float = np.inf
    shortest_direction: float = 0.0
    #: uint32 0-d (one mask for all) or (R,): the rays' masks (ray_masks)
    mask: np.ndarray = dataclasses.field(default_factory=lambda: np.array(ALL_BITS, np.uint32))

    def __len__(self) -> int:
        return len(self.origins)

    def name_origin(self, row: int) -> str:
        """The caller's name for the origin of flat row ``row``, and its value."""
        return _name_row(self.origin_source or _Vectors("origins", self.origins), row, self.shape)

    def name_direction(self, row: int) -> str:
        """The caller's name for the direction of flat row ``row``, and its value."""
        return _name_row(self.direction_source or _Vectors("directions", self.directions), row,
                         self.shape)


def _name_row(source: "_Vectors", row: int, shape: tuple) -> str:
    index = source.index_of(row, shape)
    return f"{source.label(index)} = {source.values(index)}"


# -- scalar arguments: one check each for integers, numbers, vectors -----------
#
# The API, the renderer and scene files all check their scalar arguments here.
# An error carries the argument's name, what was expected and what was got,
# so that each caller words it its own way: "width must be an integer >= 1
# and <= 16384, got 0" (str of the error), or a scene file's
# "scene.toml: render.width: expected an integer >= 1 and <= 16384, got 0".

#: What a number may be: not a bool, nor a complex (np.number), whose
#: imaginary part float() would drop.
REAL = (int, float, np.integer, np.floating)


class _Bad:
    def __init__(self, name: str, expected: str, got: str):
        super().__init__(f"{name} must be {expected}, got {got}")
        self.name, self.expected, self.got = name, expected, got


class BadType(_Bad, TypeError):
    """An argument of the wrong kind (a string for a number, say)."""


class BadValue(_Bad, ValueError):
    """An argument of the right kind but out of range, or not finite."""


def describe(value) -> str:
    """A value as an error shows it: its kind and a short repr."""
    kinds = {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
             list: "an array", tuple: "an array", dict: "a table"}
    kind = next((name for t, name in kinds.items() if type(value) is t), type(value).__name__)
    shown = repr(value)
    return f"{kind} {shown if len(shown) <= 40 else shown[:37] + '...'}"


def _bounds(low, high, low_open: bool = False, high_open: bool = False) -> str:
    def spelled(bound) -> str:  # an integer bound in full (2147483647, not 2.14748e+09)
        return str(bound) if isinstance(bound, (int, np.integer)) else f"{bound:g}"

    parts = []
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {spelled(low)}")
    if high is not None:
        parts.append(f"{'<' if high_open else '<='} {spelled(high)}")
    return "".join(f" {part}" if i == 0 else f" and {part}" for i, part in enumerate(parts))


def integer(name: str, value, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an int: a Python or numpy integer (not a bool) within
    [low, high]; else BadType or BadValue naming ``name``."""
    expected = "an integer" + _bounds(low, high)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise BadType(name, expected, describe(value))
    if (low is not None and value < low) or (high is not None and value > high):
        raise BadValue(name, expected, str(value))
    return int(value)


def number(name: str, value, low: float | None = None, high: float | None = None,
           low_open: bool = False, high_open: bool = False) -> float:
    """``value`` as a finite float: a real number (not a bool nor a complex)
    within the bounds (open where asked); else BadType or BadValue naming
    ``name``.  A Python or TOML integer past float's range is refused by
    name, not by an OverflowError."""
    expected = "a finite number" + _bounds(low, high, low_open, high_open)
    if isinstance(value, bool) or not isinstance(value, REAL):
        raise BadType(name, "a number", describe(value))
    try:
        result = float(value)
    except OverflowError:  # integers have no bound
        raise BadValue(name, "a finite number", f"an integer of {value.bit_length()} bits, "
                                                "beyond float's range") from None
    too_low = low is not None and (result <= low if low_open else result < low)
    too_high = high is not None and (result >= high if high_open else result > high)
    if not math.isfinite(result) or too_low or too_high:
        raise BadValue(name, expected, str(value))
    return result


def vector3(name: str, value, low: float | None = None, high: float | None = None,
            low_open: bool = False) -> np.ndarray:
    """Three numbers [x, y, z] (a list, tuple or array) as float64 (3,),
    each checked by ``number`` as ``name[k]`` (so a bad element is named);
    a masked, ragged or non-numeric array, or another count, is an error
    naming ``name``."""
    array = as_array(name, value)  # masked and ragged arrays, tensors
    listed = isinstance(value, (list, tuple))
    if array.dtype.kind not in "fiuO" and not (listed and len(value) == 3):
        raise BadType(name, "3 numbers [x, y, z]", describe(value))
    if len(value if listed else array.reshape(-1)) != 3 or (not listed and array.ndim != 1):
        raise BadValue(name, "3 numbers [x, y, z]", describe(value))
    items = value if listed else array.tolist()
    return np.array([number(f"{name}[{k}]", item, low, high, low_open)
                     for k, item in enumerate(items)], np.float64)


def color(name: str, value, high: float = 1.0) -> np.ndarray:
    """An RGB value: one number (grey) or three, each in [0, high], as
    float64 (3,); each checked by ``number`` (a bad channel is named)."""
    if isinstance(value, REAL) and not isinstance(value, bool):
        return np.repeat(number(name, value, 0.0, high), 3)
    if isinstance(value, (str, bytes, dict)):
        raise BadType(name, "a number or 3 numbers [r, g, b]", describe(value))
    return vector3(name, value, 0.0, high)


def unmasked(name: str, value):
    """``value``, unless it is a masked array with masked entries: np.asarray
    would drop the mask and keep what it hides."""
    if np.ma.is_masked(value):
        raise ValueError(f"{name} is a masked array with masked entries: fill or drop them "
                         "first (e.g. .filled(np.nan) or .compressed())")
    return value


#: What a real-valued input may hold, for the messages.
REAL_DTYPES = ("float32 (used as it is), or float64, float16, bfloat16 or integers (converted "
               "to float32)")


def _from_tensor(value):
    """A PyTorch tensor as numpy reads it: detached (results carry no
    gradient, and numpy refuses a tensor that requires one), on the CPU,
    and bfloat16, which numpy has no type for, widened to float32 (exact).
    Anything else is returned as it is."""
    if type(value).__module__.partition(".")[0] != "torch" or not hasattr(value, "detach"):
        return value
    value = value.detach()
    if value.device.type != "cpu":
        value = value.cpu()
    if str(value.dtype) == "torch.bfloat16":
        value = value.float()
    return value.numpy()


def _not_on_a_device(name: str, value) -> None:
    """The TypeError naming ``name`` for a pyopencl array where a host array
    is taken: numpy would read it as one object.  (The ray and point
    queries take arrays on the device before they get here:
    query/on_device.py.)"""
    if type(value).__module__.startswith("pyopencl") and hasattr(value, "get"):
        raise TypeError(f"{name} is a pyopencl array: this call takes host arrays (the ray "
                        f"and point queries take them on the device); pass "
                        f"{name}.get() (a numpy copy)")


def as_array(name: str, value) -> np.ndarray:
    """``value`` as a numpy array (unmasked; a PyTorch tensor detached and on
    the CPU; bfloat16, as JAX's ml_dtypes gives it, as float32), or the
    ValueError naming ``name`` when it is ragged (nested lists of unequal
    lengths) or cannot be read as an array."""
    unmasked(name, value)
    _not_on_a_device(name, value)
    value = _from_tensor(value)
    try:
        array = np.asarray(value)
    except (ValueError, TypeError) as error:
        ragged = isinstance(value, (list, tuple)) or "inhomogeneous" in str(error)
        what = "is not a rectangular array" if ragged else "cannot be read as a numpy array"
        raise ValueError(f"{name} {what}: {error}") from None
    if array.dtype.name == "bfloat16":
        return array.astype(np.float32)
    return array


def _big_integers(name: str, array: np.ndarray) -> np.ndarray:
    """An object array whose elements are all real numbers (numpy keeps a
    Python integer past int64 as an object, 10**30) as float64, or the
    BadValue naming ``name`` for one past float64; any other array as it
    is."""
    flat = array.ravel()
    if not flat.size or not all(isinstance(x, REAL) and not isinstance(x, bool) for x in flat):
        return array
    try:
        return array.astype(np.float64)
    except OverflowError:
        big = max((x for x in flat if isinstance(x, int)), key=abs)
        raise BadValue(name, "finite numbers", f"an integer of {big.bit_length()} bits, past "
                       f"float64's range") from None


def numeric_array(name: str, value) -> np.ndarray:
    """``value`` as a numpy array of real numbers, or the error naming ``name``."""
    array = as_array(name, value)
    if array.dtype == object:
        array = _big_integers(name, array)
    if array.dtype.kind not in "fiu":  # not bool, nor timedelta64 (a numpy integer)
        raise TypeError(f"{name} must hold real numbers, got dtype {array.dtype}; expected "
                        f"{REAL_DTYPES}")
    return array


class _Vectors:
    """One (..., 3) input: as the caller gave it (for messages) and its name.
    ``part`` picks the columns of a packed (..., 6) array."""

    def __init__(self, name: str, given: np.ndarray, part: slice | None = None):
        self.name, self.given, self.part = name, given, part
        self.lead = given.shape[:-1]

    def values(self, index: tuple):
        row = self.given[index]
        return (row[self.part] if self.part is not None else row).tolist()

    def label(self, index: tuple) -> str:
        where = ", ".join(str(i) for i in index)
        suffix = "" if self.part is None else f"[{self.part.start or 0}:{self.part.stop or ''}]"
        return f"{self.name}[{where}]{suffix}" if index else f"{self.name}{suffix}"

    def index_of(self, row: int, shape: tuple) -> tuple:
        """The index into the given array of flat row ``row`` of the
        broadcast rows of leading shape ``shape``."""
        full = np.unravel_index(row, shape) if shape else ()
        own = full[len(full) - len(self.lead):] if self.lead else ()
        return tuple(0 if size == 1 else int(i) for i, size in zip(own, self.lead))


def vectors(name: str, value, width: int = 3) -> np.ndarray:
    array = numeric_array(name, value)
    if array.ndim < 1 or array.shape[-1] != width:
        shape = "(..., 3)" if width == 3 else "(..., 6): origin then direction"
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    return array


def _as_rows(array: np.ndarray, shape: tuple) -> np.ndarray:
    """(prod(shape), 3) float32 C-contiguous and aligned (the kernels may read
    it in place), broadcast from ``array``; values are checked later."""
    with np.errstate(over="ignore", invalid="ignore"):  # reported by row, later
        rows = np.broadcast_to(array, shape + (3,)).reshape(-1, 3)
        return np.require(rows, np.float32, ["C_CONTIGUOUS", "ALIGNED"])


def rays(origins, directions=None, tmin=0.0, tmax=np.inf) -> Rays:
    """Checks and flattens a batch of rays (see the module's docstring)."""
    if directions is None:
        packed = vectors("rays", origins, width=6)
        sources = [_Vectors("rays", packed, slice(0, 3)), _Vectors("rays", packed, slice(3, 6))]
        o, d = packed[..., :3], packed[..., 3:]
    else:
        o, d = vectors("origins", origins), vectors("directions", directions)
        sources = [_Vectors("origins", o), _Vectors("directions", d)]
    shape = ray_shape(o.shape, d.shape)
    _check_batch("rays", shape)
    o_rows, d_rows = _as_rows(o, shape), _as_rows(d, shape)
    if np.may_share_memory(o_rows, d_rows):  # two host-pointer buffers must not overlap
        d_rows = d_rows.copy()
    extent = _rays_are_valid(o_rows, d_rows)
    if extent is None:
        _raise_first_bad_row(sources[0], o_rows, shape, directions=False)
        _raise_first_bad_row(sources[1], d_rows, shape, directions=True)
        raise RuntimeError("hlbvh_cl internal error: a block of rays failed its check but no "
                           "row did")
    low, high = limits("tmin", tmin, shape), limits("tmax", tmax, shape)
    check_limits(low, high, shape)
    return Rays(o_rows, d_rows, *inward(low, high), shape, sources[0], sources[1], *extent)


def inward(low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The limits (limits()) as float32, tmin rounded up and tmax down: the
    kernels compare float32 t, and every t they then take meets the limits
    as given (rounding to nearest would take t = float32(0.1) > 0.1 under
    tmax = 0.1).  A tmax past float32's range becomes its largest value."""
    return _rounded(low, np.inf), _rounded(high, -np.inf)


def _rounded(limit: np.ndarray, toward: float) -> np.ndarray:
    """``limit`` as C-contiguous float32, rounded toward ``toward`` where
    float32 cannot hold it.  A float32 limit is its own value: kept as it
    is (no float64 copy and compare; a copy only to make it contiguous)."""
    if limit.dtype == np.float32:
        return np.require(limit, np.float32, ["C_CONTIGUOUS", "ALIGNED"])
    with np.errstate(over="ignore"):
        limit32 = limit.astype(np.float32)
    moved = limit32 < limit if toward > 0 else limit32 > limit
    return np.where(moved, np.nextafter(limit32, np.float32(toward)), limit32).astype(
        np.float32, copy=False)


def ray_shape(origins_shape: tuple, directions_shape: tuple) -> tuple:
    """The rays' leading shape: origins' and directions' broadcast together."""
    try:
        return np.broadcast_shapes(origins_shape[:-1], directions_shape[:-1])
    except ValueError:
        raise ValueError(f"origins of shape {origins_shape} and directions of shape "
                         f"{directions_shape} do not broadcast together (give one origin (3,) "
                         "for all, or one per direction)") from None


def _check_batch(what: str, shape: tuple) -> None:
    """Refuses a batch larger than MAX_BATCH, before it is flattened."""
    count = math.prod(shape)
    if count > MAX_BATCH:
        raise ValueError(f"{count} {what} in one call (leading shape {shape}): at most "
                         "2**32 - 1 fit the kernels' uint32 indices; split the batch")


def points(value, name: str = "points") -> tuple[np.ndarray, tuple]:
    """Query points (..., 3) as (N, 3) float32 C-contiguous rows, and their
    leading shape; a point that is not finite in float32 is named."""
    array = vectors(name, value)
    shape = array.shape[:-1]
    _check_batch(name, shape)
    rows = _as_rows(array, shape)
    # min() and max() propagate NaN: two fast passes, no temporary (isfinite
    # then all(axis=1) over rows of three goes element by element)
    if len(rows) and not (np.isfinite(rows.min()) and np.isfinite(rows.max())):
        source = _Vectors(name, array)
        _raise_first_bad_row(source, rows, shape, directions=False)
    return rows, shape


def _rows_are_valid(origins: np.ndarray, directions: np.ndarray, start: int,
                    stop: int) -> tuple[float, float] | None:
    """None unless the rays [start, stop) have finite origins and finite
    directions with a component of magnitude >= _TINY; else the largest
    origin component magnitude, and a lower bound on each direction's
    largest component magnitude (exact below _SHORT; see Rays).  One pass,
    block by block.  min() and max() propagate NaN, so they test finiteness
    without a temporary; a direction's magnitudes serve both of its tests,
    and only a block that holds a small component looks at its rows."""
    magnitudes = np.empty((min(CHECK_BLOCK, stop - start), 3), np.float32)
    longest = np.empty(len(magnitudes), np.float32)
    farthest, shortest = 0.0, np.inf
    for first in range(start, stop, CHECK_BLOCK):
        last = min(first + CHECK_BLOCK, stop)
        block = origins[first:last]
        low, high = block.min(), block.max()
        if not (np.isfinite(low) and np.isfinite(high)):
            return None
        farthest = max(farthest, -float(low), float(high))
        size = np.abs(directions[first:last], out=magnitudes[:last - first])
        if not np.isfinite(size.max()):
            return None
        least = size.min()
        if least < _SHORT:
            # each row's largest, column by column (max(axis=1) over rows of
            # three goes element by element, many times slower)
            rows = longest[:last - first]
            np.maximum(size[:, 0], size[:, 1], out=rows)
            least = np.maximum(rows, size[:, 2], out=rows).min()
            if least < _TINY:
                return None
        shortest = min(shortest, float(least))
    return farthest, shortest


_check_pool: ThreadPoolExecutor | None = None
_check_pool_lock = threading.Lock()


def _check_threads() -> ThreadPoolExecutor:
    """The threads the checks of large batches are split over (one per CPU;
    numpy releases the GIL inside its reductions)."""
    global _check_pool
    with _check_pool_lock:
        if _check_pool is None:
            _check_pool = ThreadPoolExecutor(max_workers=os.cpu_count() or 1,
                                             thread_name_prefix="hlbvh_cl-checks")
        return _check_pool


def _rays_are_valid(origins: np.ndarray, directions: np.ndarray) -> tuple[float, float] | None:
    """_rows_are_valid over every ray, a run of blocks per thread for large
    batches."""
    count = len(origins)
    blocks = -(-count // CHECK_BLOCK)
    parts = min(os.cpu_count() or 1, blocks)
    if parts <= 1:
        return _rows_are_valid(origins, directions, 0, count)
    step = -(-blocks // parts) * CHECK_BLOCK
    bounds = [(first, min(first + step, count)) for first in range(0, count, step)]
    rest = [_check_threads().submit(_rows_are_valid, origins, directions, *b) for b in bounds[1:]]
    found = [_rows_are_valid(origins, directions, *bounds[0])]
    found += [future.result() for future in rest]
    if any(part is None for part in found):
        return None
    return max(part[0] for part in found), min(part[1] for part in found)


def _raise_first_bad_row(source: _Vectors, rows: np.ndarray, shape: tuple,
                         directions: bool) -> None:
    """Raises the ValueError naming the first bad row of ``rows`` (float32,
    flat) by its index in the array the caller gave, if it has one."""
    finite = np.isfinite(rows).all(axis=1)
    if not finite.all():
        index = source.index_of(int(np.argmin(finite)), shape)
        given = np.asarray(source.values(index), dtype=np.float64)
        why = "is not finite" if not np.isfinite(given).all() else "overflows float32"
        raise ValueError(f"{source.label(index)} = {source.values(index)} {why}")
    if directions:
        short = np.flatnonzero(np.abs(rows).max(axis=1) < _TINY)
        if len(short):
            row = int(short[0])
            what = ("has zero length" if not rows[row].any()
                    else "is too short to invert (subnormal)")
            index = source.index_of(row, shape)
            raise ValueError(f"{source.label(index)} = {shown(rows[row])} {what}; "
                             "a direction needs a component of magnitude >= 1.2e-38")


def limits(name: str, value, shape: tuple) -> np.ndarray:
    """A scalar (0-d), or the rays' (R,) values broadcast from an array of a
    shape that broadcasts to theirs; no NaN.  float32 as given (inward keeps
    it exactly), any other type as float64 (inward rounds it)."""
    array = numeric_array(name, value)
    if array.dtype != np.float32:
        array = array.astype(np.float64, copy=False)
    # min() propagates NaN: one pass, no temporary, then the NaN's place
    if array.size and np.isnan(array.min()):
        nan = np.isnan(array)
        index = np.unravel_index(int(np.argmax(nan.reshape(-1))), array.shape)
        where = f"{name}[{', '.join(str(int(i)) for i in index)}]" if array.ndim else name
        raise ValueError(f"{where} is NaN")
    if array.ndim == 0:
        return array
    return _per_ray(name, array, shape)


def _per_ray(name: str, array: np.ndarray, shape: tuple) -> np.ndarray:
    """``array`` broadcast to the rays' leading shape, flat (R,), or the
    error naming ``name``."""
    check_per_ray_shape(name, array.shape, shape)
    return np.broadcast_to(array, shape).reshape(-1)


def check_per_ray_shape(name: str, given: tuple, shape: tuple) -> None:
    """The error naming ``name`` unless its shape ``given`` broadcasts to the
    rays' leading shape."""
    try:
        if np.broadcast_shapes(given, shape) != shape:
            raise ValueError
    except ValueError:
        raise ValueError(f"{name} has shape {given}, which does not broadcast to the "
                         f"rays' shape {shape}") from None


def ray_masks(value, shape: tuple) -> np.ndarray:
    """uint32 masks for rays of leading shape ``shape``: one for all (0-d)
    or one per ray (R,), broadcast from an array of integers (mask_bits)."""
    array = as_array("mask", value)
    if array.dtype.kind not in "iu":  # not bool, nor timedelta64 (a numpy integer)
        raise TypeError(f"mask must hold integers (32-bit masks), got dtype {array.dtype}")
    bits = mask_bits(array, "mask")
    if array.ndim == 0:
        return bits
    return np.ascontiguousarray(_per_ray("mask", bits, shape), np.uint32)


def mask_bits(array: np.ndarray, name: str) -> np.ndarray:
    """uint32 bit patterns of an integer array of masks called ``name``,
    each in [-2^31, 2^32): a negative one stands for its 32-bit two's
    complement, as Python's ~2 for every bit but bit 1.  Else the
    ValueError that names the first that does not fit."""
    outside = (array < -2**31) | (array > ALL_BITS)
    if outside.any():
        index = np.unravel_index(int(np.argmax(outside.reshape(-1))), array.shape)
        where = f"{name}[{', '.join(str(int(i)) for i in index)}]" if array.ndim else name
        raise ValueError(f"{where} = {int(array[index])} does not fit 32 bits")
    return (array.astype(np.int64) & ALL_BITS).astype(np.uint32)


def shown(row: np.ndarray) -> str:
    """A float32 row as a message shows it: each value in the fewest digits
    that give it back (0.1, not tolist's 0.10000000149011612)."""
    return f"[{', '.join(str(value) for value in row)}]"


def row_name(name: str, row: int, shape: tuple) -> str:
    """``name`` indexed at flat row ``row`` of leading shape ``shape``."""
    index = np.unravel_index(row, shape) if len(shape) > 1 else (row,)
    return f"{name}[{', '.join(str(int(i)) for i in index)}]"


def check_limits(tmin: np.ndarray, tmax: np.ndarray, shape: tuple) -> None:
    # limits() left no NaN: min() and max() in one pass each, no temporary
    if tmin.size and not (tmin.min() >= 0 and tmin.max() < np.inf):
        bad = (tmin < 0) | ~np.isfinite(tmin)
        row = int(np.argmax(bad.reshape(-1)))
        where = row_name("tmin", row, shape) if tmin.ndim else "tmin"
        raise ValueError(f"{where} = {tmin.reshape(-1)[row]} must be finite and >= 0")
    inverted = tmin > tmax
    if inverted.ndim == 0 and inverted:
        raise ValueError(f"tmin = {float(tmin)} is greater than tmax = {float(tmax)}")
    if inverted.any():
        row = int(np.argmax(inverted))
        count = len(inverted)
        low = float(np.broadcast_to(tmin, (count,))[row])
        high = float(np.broadcast_to(tmax, (count,))[row])
        ray = row_name("", row, shape)[1:-1]
        raise ValueError(f"ray {ray}: tmin[{ray}] = {low} is greater than tmax[{ray}] = {high}")


# -- meshes ------------------------------------------------------------------

#: Vertices and faces a mesh may have: its kernels index them with int32.
_INT32_LIMIT = 2**31


def _mesh_shape(name: str, array: np.ndarray, rows: str) -> None:
    if array.size == 0:
        raise ValueError(f"{name} is empty (shape {array.shape}): a mesh needs at least one "
                         f"{'vertex' if name == 'vertices' else 'triangle'}")
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} has shape {array.shape}, expected ({rows}, 3)")


def _first_row(mask: np.ndarray) -> int:
    """Index of the first row of a (rows, 3) boolean mask with any True."""
    return int(np.flatnonzero(mask.any(axis=1))[0])


def mesh_vertices(vertices) -> np.ndarray:
    """A mesh's vertices as Mesh stores them: (N, 3) float32, C-contiguous,
    read-only, a copy; errors name the first bad row."""
    array = as_array("vertices", vertices)
    if array.dtype.kind not in "fiu":
        raise TypeError(f"vertices has dtype {array.dtype}, expected real numbers (float32 "
                        f"preferred; any float or integer dtype is converted)")
    _mesh_shape("vertices", array, "N")
    if array.shape[0] >= _INT32_LIMIT:
        raise ValueError(f"vertices has {array.shape[0]} rows; at most 2**31 - 1 fit int32 indices")
    if array.dtype.kind == "f":
        finite = np.isfinite(array)
        if not finite.all():
            row = _first_row(~finite)
            raise ValueError(f"vertices[{row}] = {array[row].tolist()} is not finite (NaN or inf)")
    with np.errstate(over="ignore"):
        converted = np.array(array, dtype=np.float32, order="C", copy=True)
    overflow = ~np.isfinite(converted)
    if overflow.any():
        row = _first_row(overflow)
        raise ValueError(f"vertices[{row}] = {array[row].tolist()} overflows float32 "
                         f"(|x| > {np.finfo(np.float32).max:.3g})")
    converted.flags.writeable = False
    return converted


def check_mesh_scale(vertices, faces: np.ndarray) -> None:
    """Refuses a mesh (``vertices`` as given, ``faces`` checked) whose used
    coordinates are all below float32's normal range: they round to
    subnormals or 0, and the mesh, its shape lost, would be missed
    silently.  The vertices the faces use, as the scene's frame takes them:
    an unused vertex of 1 had let such a mesh through."""
    array = as_array("vertices", vertices)
    if array.dtype.kind != "f" or not len(faces):
        return
    tiny = np.finfo(np.float32).tiny
    largest = np.abs(array).max(axis=1)
    normal = largest >= tiny
    if normal.all() or normal[faces].any():  # (the first: no gather of the faces' rows)
        return
    used = faces.ravel()
    at = int(np.argmax(largest[used]))
    if largest[used[at]] > 0:
        row = int(used[at])
        raise ValueError(f"the vertices the faces use are all below float32's normal range "
                         f"(the largest, vertices[{row}] = {array[row].tolist()}, is under "
                         f"{tiny:.3g}): in float32 the mesh would lose "
                         "its shape; scale it up")


def mesh_faces(faces, vertex_count: int) -> np.ndarray:
    """A mesh's faces as Mesh stores them: (M, 3) int32 indices below
    vertex_count, C-contiguous, read-only, a copy."""
    array = as_array("faces", faces)
    if array.size == 0:  # [] reads as float64: say it is empty, not float
        _mesh_shape("faces", array, "M")
    if array.dtype.kind == "f":
        raise TypeError(f"faces has dtype {array.dtype}: pass integers (e.g. faces.astype(np.int32))")
    if array.dtype.kind not in "iu":
        raise TypeError(f"faces has dtype {array.dtype}, expected integer vertex indices")
    _mesh_shape("faces", array, "M")
    if array.shape[0] >= _INT32_LIMIT:
        raise ValueError(f"faces has {array.shape[0]} rows; at most 2**31 - 1 fit int32 ids")
    if array.dtype.kind == "i":
        negative = array < 0
        if negative.any():
            row = _first_row(negative)
            raise ValueError(f"faces[{row}] = {array[row].tolist()}: index "
                             f"{int(array[row][negative[row]][0])} is negative")
    too_large = array >= min(vertex_count, _INT32_LIMIT)
    if too_large.any():
        row = _first_row(too_large)
        value = int(array[row][too_large[row]][0])
        if value >= _INT32_LIMIT:
            raise ValueError(f"faces[{row}] = {array[row].tolist()}: index {value} does not fit "
                             f"int32 (>= 2**31)")
        raise ValueError(f"faces[{row}] = {array[row].tolist()}: index {value} is out of range "
                         f"for {vertex_count} vertices (expected 0 <= index < {vertex_count})")
    converted = np.array(array, dtype=np.int32, order="C", copy=True)
    converted.flags.writeable = False
    return converted


def spheres(value) -> np.ndarray:
    """A Scene's analytic spheres: (S, 4) rows of centre x, y, z and radius,
    as float64 (a copy); None is (0, 4).  Errors name the first bad row."""
    if value is None:
        return np.zeros((0, 4))
    array = as_array("spheres", value)
    if array.shape in ((0,), (0, 4)):
        return np.zeros((0, 4))  # [] or (0, 4): none
    if array.dtype.kind not in "fiu":
        raise TypeError(f"spheres has dtype {array.dtype}, expected real numbers: rows of "
                        "centre x, y, z and radius")
    if array.ndim != 2 or array.shape[1] != 4:
        raise ValueError(f"spheres has shape {array.shape}, expected (S, 4): rows of centre "
                         "x, y, z and radius")
    # C order: the rows go to the device as float4 records as they lie in memory
    array = np.array(array, dtype=np.float64, order="C", copy=True)
    limit = float(np.finfo(np.float32).max)
    bad = ~(np.isfinite(array).all(axis=1) & (np.abs(array) <= limit).all(axis=1))
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise ValueError(f"spheres[{row}] = {array[row].tolist()} is not finite in float32")
    tiny = float(np.finfo(np.float32).tiny)
    small = ~(array[:, 3] >= tiny)
    if small.any():
        row = int(np.flatnonzero(small)[0])
        raise ValueError(f"spheres[{row}] has radius {array[row, 3]:g}: a sphere's radius must "
                         f"be positive (at least {tiny:.3g}, float32's smallest normal)")
    return array
