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
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..core.paths import kernel_of
from ..device.runtime import Runtime

KERNEL = kernel_of(__name__)


class Film:
    """A render's device buffers: the accumulators of one pass of pixels,
    and the whole image; grow-only, reused across renders."""

    def __init__(self):
        self.pixels = 0         # accumulators held
        self.image_bytes = 0    # image bytes held
        self.accum: cl.Buffer | None = None
        self.image: cl.Buffer | None = None

    @staticmethod
    def sizes(pixels: int, image_pixels: int, hdr: bool = False) -> dict[str, int]:
        """Bytes of the film's buffers for a pass of ``pixels`` pixels
        (``hdr``: a float32 image)."""
        return {"accumulated colour": 16 * pixels, "image": (12 if hdr else 3) * image_pixels}

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

    def read(self, rt: Runtime, image: np.ndarray) -> cl.Event:
        """Enqueues the image's copy into ``image`` (height, width, 3),
        uint8 or float32 as encoded or resolved."""
        return cl.enqueue_copy(rt.queue, image, self.image, is_blocking=False)
