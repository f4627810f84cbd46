"""The environment map light (emitters.py's "envmap"): Mitsuba 3's
``envmap`` emitter, an equirectangular (latitude-longitude) image of the
radiance arriving from every direction at infinity.

Mapping, as Mitsuba's (src/emitters/envmap.cpp), so that one file lights a
scene alike in both renderers.  A world direction d is taken to the map's
frame by the inverse of ``to_world`` (a rotation), and there

    u = atan2(d.x, -d.z) / (2 pi)  (wrapped into [0, 1)),  v = acos(d.y) / pi

(the top row looks along +y; the image's left edge, u = 0, along -z; its
middle, u = 0.5, along +z; u = 0.25 along +x).  The radiance is the image's bilinear
interpolation with texel-centred columns (column i at u = (i + 0.5) / W,
periodic in u) and corner-aligned rows (row j at v = j / (H - 1), clamped),
times ``scale``.  Images smaller than 2 x 3 (width x height) are padded by
repeating their last column and row, as Mitsuba pads them.

Importance sampling: the bilinear patches between four neighbouring texels
are the cells, (H - 1) x W of them, each a band of latitude
[theta_j, theta_j+1] by a sector of longitude.  A cell's value is the mean
luminance of its four corners.  The path integrator's light samples pick a
cell with probability proportional to how far its value exceeds the map's
mean over the sphere (0 where it does not) times its solid angle (the
integral of sin(theta) over it), by a marginal CDF over the bands and a
conditional CDF per band, built here in float64; a direction is then
uniform in solid angle within the cell.  That is MIS compensation (Karlik
et al. 2019, "MIS Compensation: Optimizing Sampling Techniques in Multiple
Importance Sampling"), as pbrt-v4's ImageInfiniteLight samples for its
PathIntegrator: BSDF sampling, the other strategy, already covers the
map's even part, as it covers a constant environment alone
(integrators/path.py), so light samples go where the map stands out, a
sun above all; directions where the density is 0 are reached by BSDF
sampling with the full weight.  A map with nothing above its mean takes
no light samples.  The density is piecewise constant: P(cell) / solid
angle(cell), and the kernels evaluate exactly that density for a
direction found by BSDF sampling (MIS weights stay correct although the
density is not proportional to the bilinear radiance).
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core import inputs
from .film import BRIGHTEST

#: Mitsuba pads smaller images to this width and height (Bitmap::pad_to).
MIN_WIDTH, MIN_HEIGHT = 2, 3

#: Rec. 709 luminance weights: how bright an RGB radiance is, for light
#: selection and the map's sampling (Mitsuba's luminance()).
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

#: The largest side read: the kernels index pixels with uint32.
MAX_SIDE = 1 << 15

_FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True, eq=False)
class Envmap:
    """A checked environment map: ``image`` float32 (H, W, 3), padded and
    times ``scale``; ``to_world`` the float64 3 x 3 rotation from the map's
    frame to the world; ``name`` how errors and reprs call it."""
    image: np.ndarray
    to_world: np.ndarray
    name: str

    @functools.cached_property
    def tables(self) -> tuple[np.ndarray, float]:
        """(float32 CDFs, total): the H - 1 entries of the marginal CDF over
        the bands, then each band's W entries of its conditional CDF, by
        each cell's value above the mean (the module's docstring); and the
        integral over the sphere of the luminance above the mean, in float64
        (light selection's power; 0: no light samples)."""
        height, width, _ = self.image.shape
        lum = np.asarray(self.image, np.float64) @ LUMINANCE
        corners = 0.25 * (lum[:-1] + lum[1:] + np.roll(lum[:-1], -1, 1) + np.roll(lum[1:], -1, 1))
        theta = np.pi * np.arange(height) / (height - 1)
        # cos(theta_j) - cos(theta_j+1) without cancellation near the poles
        band = 2.0 * np.sin(0.5 * (theta[:-1] + theta[1:])) * np.sin(0.5 * np.pi / (height - 1))
        solid = np.broadcast_to((band * (2.0 * np.pi / width))[:, None], corners.shape)
        mean = float((corners * solid).sum() / solid.sum())
        # above the mean by more than float32's rounding (a map of one value:
        # nothing, where its cells' sums round apart)
        weights = np.maximum(corners - mean * (1.0 + 1e-6), 0.0) * solid
        rows = weights.sum(1)
        total = float(rows.sum())
        conditional = np.where(rows[:, None] > 0, np.cumsum(weights, 1)
                               / np.where(rows > 0, rows, 1.0)[:, None],
                               np.arange(1, width + 1) / width)
        marginal = np.cumsum(rows) / total if total > 0 else np.arange(1, height) / (height - 1)
        conditional[:, -1] = 1.0
        marginal[-1] = 1.0
        cdf = np.concatenate([marginal, conditional.reshape(-1)]).astype(np.float32)
        return cdf, total


def check_envmap(name: str, spec) -> Envmap:
    """An "envmap" emitter spec (emitters.py) -> Envmap; errors name
    ``name``, the file, the pixel."""
    has_file, has_image = "filename" in spec, "image" in spec
    if has_file == has_image:
        raise ValueError(f"{name}: envmap needs its 'filename' or an 'image' array "
                         "(H, W, 3), one of them")
    if has_file:
        filename = spec["filename"]
        if not isinstance(filename, (str, os.PathLike)):
            raise TypeError(f"{name}['filename'] must be a path, got {inputs.describe(filename)}")
        what = f"{name}['filename'] {os.fspath(filename)}"
        try:
            image = read_radiance(filename)
        except ValueError as error:
            raise ValueError(f"{name}: {error}") from None
    else:
        what = f"{name}['image']"
        image = spec["image"]
        if not isinstance(image, np.ndarray) or image.dtype.kind not in "fiu":
            raise TypeError(f"{what} must be a numpy array of floats (H, W, 3), got "
                            f"{inputs.describe(image)}")
    if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < 1:
        raise ValueError(f"{what}: expected an (H, W, 3) RGB image, got shape {image.shape}")
    if max(image.shape[:2]) > MAX_SIDE:
        raise ValueError(f"{what}: {image.shape[1]} x {image.shape[0]} pixels, more than "
                         f"{MAX_SIDE} on a side")
    if not (np.isfinite(image).all() and (image >= 0).all()):
        y, x, c = (int(k) for k in np.argwhere(~np.isfinite(image) | (image < 0))[0])
        raise ValueError(f"{what}: pixel (row {y}, column {x}) channel {c} is {image[y, x, c]}:"
                         f" radiance must be finite and >= 0")
    scale = inputs.number(f"{name}['scale']", spec.get("scale", 1.0), 0.0, _FLOAT32_MAX)
    if float(image.max(initial=0)) * scale > BRIGHTEST:
        raise ValueError(f"{what} times scale {scale} is brighter than {BRIGHTEST:g}, "
                         "which the film's float32 sums could not hold")
    scaled = image.astype(np.float32) * np.float32(scale)  # Mitsuba scales in float32 too
    height, width = image.shape[:2]
    if height < MIN_HEIGHT or width < MIN_WIDTH:
        scaled = np.pad(scaled, ((0, max(0, MIN_HEIGHT - height)),
                                 (0, max(0, MIN_WIDTH - width)), (0, 0)), mode="edge")
    rotation = to_world_rotation(f"{name}['to_world']", spec.get("to_world"))
    return Envmap(np.ascontiguousarray(scaled), rotation, what)


def to_world_rotation(name: str, value) -> np.ndarray:
    """A to_world of 3 x 3 or 4 x 4 (its translation ignored: directions)
    as a float64 rotation; None is the identity.  Scaling and shear are
    refused: the lat-long mapping takes unit directions."""
    if value is None:
        return np.eye(3)
    try:
        matrix = np.asarray(value, np.float64)
        numbers = np.asarray(value, object).ravel()
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a 3 x 3 or 4 x 4 matrix, got "
                        f"{inputs.describe(value)}") from None
    # numbers, not what numpy would turn into them ("1", True)
    if not all(isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(
            x, (bool, np.bool_)) for x in numbers):
        raise TypeError(f"{name} must be a 3 x 3 or 4 x 4 matrix of numbers, got "
                        f"{inputs.describe(value)}")
    if matrix.shape not in ((3, 3), (4, 4)) or not np.isfinite(matrix).all():
        raise ValueError(f"{name} must be a finite 3 x 3 or 4 x 4 matrix, got shape "
                         f"{matrix.shape}")
    if matrix.shape == (4, 4) and not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name}'s last row must be 0 0 0 1 (an affine map), got "
                         f"{matrix[3].tolist()}")
    rotation = matrix[:3, :3]
    if np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-5:
        raise ValueError(f"{name} must be a rotation (orthonormal columns): an environment map "
                         f"is only turned, got {rotation.tolist()}")
    return rotation


def read_radiance(path) -> np.ndarray:
    """The float32 (H, W, 3) linear RGB of an OpenEXR (.exr) or Radiance
    RGBE (.hdr, .rgbe) file, the top row first; an error names the file and
    why it cannot be read."""
    path = Path(os.fspath(path))
    try:
        stat = path.stat()
    except OSError as error:
        raise ValueError(f"cannot read the environment map {path}: {error.strerror}") from None
    return _read_cached(str(path.resolve()), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=4)
def _read_cached(path: str, mtime_ns: int, size: int) -> np.ndarray:
    """One file's pixels, read again only when it changes (renders check
    their emitters each time)."""
    suffix = Path(path).suffix.lower()
    try:
        if suffix == ".exr":
            image = _read_exr(path)
        elif suffix in (".hdr", ".rgbe"):
            image = _read_rgbe(Path(path).read_bytes())
        else:
            raise ValueError(f"{suffix or 'no extension'} is not an environment map format "
                             "read here (.exr, .hdr, .rgbe)")
    except (OSError, RuntimeError, ValueError, KeyError, IndexError) as error:
        raise ValueError(f"cannot read the environment map {path}: {error}") from None
    image.flags.writeable = False
    return image


#: Rec. 709's (sRGB's) primaries and white point, x and y each, as an EXR's
#: chromaticities attribute gives them: red, green, blue, white.
REC709 = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)


def _read_exr(path: str) -> np.ndarray:
    """Linear Rec. 709 RGB of an EXR's R, G and B channels (or grey from Y
    alone).  What would be read as other colours is refused: primaries
    other than Rec. 709's (Mitsuba converts them; they had been taken as
    Rec. 709, up to 59 % off), and luminance-chroma (Y, RY, BY) or XYZ
    channels (read as grey from Y).  Channels one at a time: a file whose
    channels mix half and full floats is valid."""
    import OpenEXR
    with OpenEXR.File(path, separate_channels=True) as image:
        channels, chroma = image.channels(), image.header().get("chromaticities")
        if chroma is not None and not np.allclose(chroma, REC709, atol=1e-4):
            raise ValueError(f"its chromaticities ({', '.join(f'{c:.4g}' for c in chroma)}) are "
                             "not Rec. 709's (sRGB's), which this reader takes: convert it to "
                             "Rec. 709 RGB")
        rgb = all(c in channels for c in "RGB")  # (R, G, B beside a depth Z read as RGB)
        for kind, names in (("luminance and chroma", ("RY", "BY")), ("CIE XYZ", ("X", "Z"))):
            if not rgb and any(name in channels for name in names):
                raise ValueError(f"it stores {kind} ({', '.join(sorted(channels))}); this "
                                 "reader takes R, G and B (or Y alone, grey): convert it to RGB")
        if all(c in channels for c in "RGB"):
            return np.stack([np.asarray(channels[c].pixels, np.float32) for c in "RGB"], -1)
        if "Y" in channels:  # luminance only: grey
            return np.repeat(np.asarray(channels["Y"].pixels, np.float32)[..., None], 3, -1)
        raise ValueError(f"no R, G, B (or Y) channels, only {sorted(channels)}")


def _read_rgbe(data: bytes) -> np.ndarray:
    """Radiance's RGBE format (Greg Ward, Graphics Gems II): a text header,
    "-Y H +X W", then scanlines flat or in the adaptive run-length scheme;
    a pixel is m * 2^(e - 136) per channel, as Mitsuba decodes it."""
    header_end = data.find(b"\n\n")
    if not data.startswith((b"#?", b"\n")) or header_end < 0:
        raise ValueError("not a Radiance RGBE file (no #? header)")
    header = data[:header_end].decode("latin-1")
    if "FORMAT=" in header and "FORMAT=32-bit_rle_rgbe" not in header:
        raise ValueError("only FORMAT=32-bit_rle_rgbe is read")
    line_end = data.index(b"\n", header_end + 2)
    size = data[header_end + 2:line_end].split()
    if len(size) != 4 or size[0] != b"-Y" or size[2] != b"+X":
        raise ValueError(f"only the -Y H +X W orientation is read, got {size}")
    if not (size[1].isdigit() and size[3].isdigit()) or int(size[1]) < 1 or int(size[3]) < 1:
        raise ValueError(f"the size line must give a positive height and width, got {size}")
    height, width = int(size[1]), int(size[3])
    body, at = memoryview(data), line_end + 1
    # the fewest bytes a scanline takes: run-length coded, a run of 2 bytes per 127 pixels
    # of each channel after its 4-byte marker; checked before the image is allocated
    fewest = height * min(4 * width, 4 + 8 * -(-width // 127))
    if len(data) - at < fewest:
        raise ValueError(f"its header gives {width} x {height} pixels, more than its "
                         f"{len(data) - at} bytes of scanlines can hold")
    pixels = np.zeros((height, width, 4), np.uint8)
    for y in range(height):
        try:
            at = _rgbe_scanline(body, at, pixels[y])
        except (IndexError, ValueError) as error:
            raise ValueError(f"scanline {y} of {height} is cut short or corrupt "
                             f"({error})") from None
    exponent = pixels[..., 3].astype(np.int32)
    factor = np.where(exponent > 0, np.ldexp(1.0, exponent - 136), 0.0)
    return (pixels[..., :3] * factor[..., None]).astype(np.float32)


def _rgbe_scanline(body: memoryview, at: int, out: np.ndarray) -> int:
    """One scanline of RGBE bytes from body[at:] into out (W, 4); where the
    next begins."""
    width = len(out)
    if 8 <= width < 32768 and bytes(body[at:at + 2]) == b"\x02\x02":
        at += 4  # the scanline's marker and width
        for c in range(4):
            x = 0
            while x < width:
                run = body[at] > 128  # a run of one byte, else literal bytes
                count = body[at] - 128 if run else body[at]
                if count == 0 or x + count > width:
                    raise ValueError("a run of bytes outside its scanline")
                if run:
                    out[x:x + count, c] = body[at + 1]
                    at += 2
                else:
                    out[x:x + count, c] = np.frombuffer(body[at + 1:at + 1 + count], np.uint8)
                    at += 1 + count
                x += count
        return at
    out[:] = np.frombuffer(body[at:at + 4 * width], np.uint8).reshape(width, 4)
    return at + 4 * width
