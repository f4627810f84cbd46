"""Where the OpenCL sources live: inside the wheel, or beside the package in a checkout."""
from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path:
    """hlbvh_cl's folder in the user's cache ($XDG_CACHE_HOME or ~/.cache)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hlbvh_cl"


def kernel_dir() -> Path:
    here = Path(__file__).resolve().parent
    for candidate in (here / "kernels", here.parent / "kernels"):
        if (candidate / "hlbvh.h").is_file():
            return candidate
    raise FileNotFoundError(f"hlbvh_cl: the OpenCL kernels are missing (looked in {here / 'kernels'} "
                            f"and {here.parent / 'kernels'}); reinstall the package")
