"""OpenEXR images: a render's float32 linear RGB, as the OpenEXR library
writes and reads them (ZIP compression), and a path render's AOVs beside it
as further channels named as Mitsuba 3's aov integrator names them
(AOV_CHANNELS)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: The AOV channels beside R, G, B: name -> (RenderResult field, component).
#: Mitsuba's suffixes: .R/.G/.B for colours, .X/.Y/.Z for vectors, .T for depth.
AOV_CHANNELS = {"albedo.R": ("albedo", 0), "albedo.G": ("albedo", 1), "albedo.B": ("albedo", 2),
                "normal.X": ("normal", 0), "normal.Y": ("normal", 1), "normal.Z": ("normal", 2),
                "depth.T": ("depth", None)}


def write_exr(path, rgb: np.ndarray, aovs: dict | None = None) -> None:
    """Write (height, width, 3) float32 linear RGB to ``path``, with
    ``aovs`` ({"albedo": (H, W, 3), "normal": (H, W, 3), "depth": (H, W)},
    as a RenderResult holds them) as the AOV_CHANNELS beside it."""
    import OpenEXR
    rgb = np.ascontiguousarray(rgb, np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"an EXR image is (height, width, 3) RGB, got shape {rgb.shape}")
    channels = {"RGB": rgb}
    if aovs is not None:
        channels = {name: np.ascontiguousarray(rgb[..., k]) for k, name in enumerate("RGB")}
        for name, (field, component) in AOV_CHANNELS.items():
            plane = np.asarray(aovs[field], np.float32)
            plane = plane if component is None else plane[..., component]
            if plane.shape != rgb.shape[:2]:
                raise ValueError(f"AOV {field} has shape {np.shape(aovs[field])}, expected the "
                                 f"image's {rgb.shape[:2]}")
            channels[name] = np.ascontiguousarray(plane)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    try:
        with OpenEXR.File(header, channels) as image:
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


def read_exr_channels(path) -> dict[str, np.ndarray]:
    """Every channel of an EXR file by its own name ("R", "albedo.R", ...):
    (height, width) float32 each."""
    import OpenEXR
    with OpenEXR.File(str(Path(path)), separate_channels=True) as image:
        return {name: np.asarray(channel.pixels, np.float32)
                for name, channel in image.channels().items()}
