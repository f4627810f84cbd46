"""OpenEXR images: a render's float32 linear RGB, as the OpenEXR library
writes and reads them (one "RGB" channel group, ZIP compression)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_exr(path, rgb: np.ndarray) -> None:
    """Write (height, width, 3) float32 linear RGB to ``path``."""
    import OpenEXR
    rgb = np.ascontiguousarray(rgb, np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"an EXR image is (height, width, 3) RGB, got shape {rgb.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    try:
        with OpenEXR.File(header, {"RGB": rgb}) as image:
            image.write(str(Path(path)))
    except (OSError, RuntimeError) as error:
        raise OSError(f"cannot write {path}: {error}") from None


def read_exr(path) -> np.ndarray:
    """The (height, width, 3) float32 RGB of an EXR file written by write_exr."""
    import OpenEXR
    with OpenEXR.File(str(Path(path))) as image:
        channels = image.channels()
        if "RGB" in channels:
            return np.asarray(channels["RGB"].pixels, np.float32)
        return np.stack([np.asarray(channels[c].pixels, np.float32) for c in "RGB"], axis=-1)
