"""The film: what a render accumulates and what it gives back.

Each pixel of a pass sums its samples' colours in a float4 (RGB and one
spare lane, 16 bytes: one aligned load); after the last sample the sums
are scaled by 1 / spp and encoded into the whole image's 8-bit RGB
(kernels/render/film.cl): channel = round(255 * c'), c' = sqrt(clamp(c,
0, 1)) for radiance (display gamma 2, which looks as 2.2 does) and
clamp(c, 0, 1) for data (normals, depth); or, for a float32 image, the
means as they are (linear radiance, or the data).  Only that image is read
back.

A progressive render (Pipeline.render of a progressive integrator) instead
adds each band's sums of every round of samples to the float32 image
(add_to_image), so that the image of the rounds done is there to read
whenever it stops; the host divides by the samples each band took.

Under a filter wider than a pixel (the path integrator's Gaussian), a
progressive render splats instead, as Mitsuba 3's film does: each round's
values go to a whole-image round buffer (store_round), and once every band
is stored each pixel gathers the filter-weighted samples around it into its
sums and weights (splat_round); the image is sums / weights.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..core.paths import kernel_of
from ..device.runtime import Runtime
from .camera import GAUSSIAN_RADIUS, SPLAT_REACH, WEIGHT_INTERVALS, filter_table

#: The brightest a light may be (a radiance, intensity or irradiance, an
#: environment map's pixels times its scale): a pixel's float32 sums add up
#: to settings.MAX_SPP samples of a light's value times path weights, and
#: this leaves them many orders of magnitude below float32's 3.4e38.
BRIGHTEST = 1e20

KERNEL = kernel_of(__name__)


class Film:
    """A render's device buffers: the accumulators of one pass of pixels,
    and the whole image; grow-only, reused across renders."""

    #: Bytes per image pixel and float4 group of the splatting buffers (the
    #: round's values and the sums), and per pixel (the filter's taps around
    #: a sample and the sum of weights).
    SPLAT_GROUP_BYTES, SPLAT_PIXEL_BYTES = 32, 4 * (2 * (2 * SPLAT_REACH + 1) + 1)

    def __init__(self):
        self.pixels = 0         # accumulators held
        self.image_bytes = 0    # image bytes held
        self.accum: cl.Buffer | None = None
        self.image: cl.Buffer | None = None
        self.splat_pixels = 0   # image pixels the splatting buffers hold
        self.splat: dict[str, cl.Buffer] = {}
        self.groups = 0         # float4 per pixel of this render's splatting

    @classmethod
    def sizes(cls, pixels: int, image_pixels: int, hdr: bool = False,
              splat_groups: int = 0) -> dict[str, int]:
        """Bytes of the film's buffers for a pass of ``pixels`` pixels
        (``hdr``: a float32 image; ``splat_groups``: float4 values per pixel
        splatted, 0 for none)."""
        out = {"accumulated colour": 16 * pixels, "image": (12 if hdr else 3) * image_pixels}
        if splat_groups:
            out["splatted samples"] = (cls.SPLAT_GROUP_BYTES * splat_groups
                                       + cls.SPLAT_PIXEL_BYTES) * image_pixels
        return out

    def reserve(self, rt: Runtime, pixels: int, image_pixels: int, hdr: bool = False) -> None:
        """Buffers for a pass of ``pixels`` and an image of ``image_pixels``
        (the caller has checked the allocation: Runtime.check_allocation)."""
        if pixels > self.pixels:
            self.accum = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 16 * pixels)  # float4
            self.pixels = pixels
        image_bytes = (12 if hdr else 3) * image_pixels
        if image_bytes > self.image_bytes:
            self.image = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, image_bytes)
            self.image_bytes = image_bytes

    def encode(self, rt: Runtime, band, width: int, spp: int, radiance: bool) -> cl.Event:
        """The band's pixels, their sums over ``spp`` samples, into the 8-bit
        image: gamma-encoded if they are ``radiance``, else as they are."""
        kernel = rt.kernel(KERNEL, "encode_image", RADIANCE=int(radiance))
        return rt.run(kernel, band.tile_range, self.accum,
                      np.uint32(width), band.first_row, band.rows, np.float32(1.0 / spp),
                      self.image)

    def resolve(self, rt: Runtime, band, width: int, spp: int) -> cl.Event:
        """The band's pixels, their means over ``spp`` samples, into the
        float32 image."""
        return rt.run(rt.kernel(KERNEL, "radiance_image", RADIANCE=1), band.tile_range,
                      self.accum, np.uint32(width), band.first_row, band.rows,
                      np.float32(1.0 / spp), self.image)

    def clear(self, rt: Runtime, image_pixels: int) -> cl.Event:
        """Zeroes the float32 image's sums (a progressive render's start)."""
        return cl.enqueue_fill_buffer(rt.queue, self.image, np.float32(0), 0, 12 * image_pixels)

    def add(self, rt: Runtime, band, width: int) -> cl.Event:
        """The band's sums added to the float32 image's."""
        return rt.run(rt.kernel(KERNEL, "add_to_image", RADIANCE=1), band.tile_range,
                      self.accum, np.uint32(width), band.first_row, band.rows, self.image)

    def start_splatting(self, rt: Runtime, image_pixels: int, groups: int) -> cl.Event:
        """Zeroed sums and weights for splatting ``groups`` float4 values per
        pixel of an image of ``image_pixels`` (the caller has checked the
        allocation with sizes(..., splat_groups=groups))."""
        if image_pixels > self.splat_pixels or groups != self.groups:
            size = {"round": 16 * groups, "sums": 16 * groups,
                    "taps": 8 * (2 * SPLAT_REACH + 1), "weights": 4}
            self.splat = {name: cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, each * image_pixels)
                          for name, each in size.items()}
            self.splat_pixels, self.groups = image_pixels, groups
        zero = np.float32(0)
        cl.enqueue_fill_buffer(rt.queue, self.splat["weights"], zero, 0, 4 * image_pixels)
        return cl.enqueue_fill_buffer(rt.queue, self.splat["sums"], zero, 0,
                                      16 * groups * image_pixels)

    def _splat_kernel(self, rt: Runtime, name: str) -> cl.Kernel:
        return rt.kernel(KERNEL, name, RADIANCE=1, GROUPS=self.groups, REACH=SPLAT_REACH,
                         WEIGHT_INTERVALS=WEIGHT_INTERVALS)

    def store_round(self, rt: Runtime, band, width: int, values: cl.Buffer, value_groups: int,
                    to_group: int, stream: int, jitter: int) -> cl.Event:
        """The band's ``value_groups`` float4 per pixel of this round (in
        tile order), as groups ``to_group``... of the round buffer; with
        group 0, the filter's weights around each sample, from where it fell
        (the camera's ``stream`` and ``jitter``)."""
        return rt.run(self._splat_kernel(rt, "store_round"), band.tile_range, values,
                      np.uint32(value_groups), np.uint32(to_group), np.uint32(width),
                      band.first_row, band.rows, np.uint32(stream), np.int32(jitter),
                      filter_table(rt, "weights"), np.float32(GAUSSIAN_RADIUS),
                      self.splat["round"], self.splat["taps"])

    def splat_round(self, rt: Runtime, width: int, height: int, stored: int) -> cl.Event:
        """The stored round's samples, those of the image's first ``stored``
        rows (all ``height`` but in a round cut short by a time budget),
        splatted onto the sums of the pixels they reach."""
        reached = min(height, stored + SPLAT_REACH)
        return rt.run(self._splat_kernel(rt, "splat_round"), (width, reached),
                      self.splat["round"], self.splat["taps"], np.uint32(width),
                      np.uint32(height), np.uint32(stored), self.splat["sums"],
                      self.splat["weights"])

    def read_splatted(self, rt: Runtime, height: int, width: int) -> np.ndarray:
        """float32 (height, width, groups, 4): each pixel's splatted sums over
        its sum of weights."""
        sums = np.empty((height, width, self.groups, 4), np.float32)
        weights = np.empty((height, width), np.float32)
        rt.wait([cl.enqueue_copy(rt.queue, sums, self.splat["sums"], is_blocking=False),
                 cl.enqueue_copy(rt.queue, weights, self.splat["weights"], is_blocking=False)])
        # in place: no second image-sized array to allocate and fault in
        return np.divide(sums, weights[:, :, None, None], out=sums)

    def read(self, rt: Runtime, image: np.ndarray) -> cl.Event:
        """Enqueues the image's copy into ``image`` (height, width, 3),
        uint8 or float32 as encoded or resolved."""
        return cl.enqueue_copy(rt.queue, image, self.image, is_blocking=False)
