"""Where the OpenCL sources live: inside the wheel, or beside the package in a checkout."""
from __future__ import annotations

import os
from pathlib import Path


def cache_root() -> Path:
    """hlbvh_cl's folder in the user's cache ($XDG_CACHE_HOME or ~/.cache)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hlbvh_cl"


def kernel_dir() -> Path:
    """The kernels' root: the folder every kernel file and #include is
    named from (``query/rays.cl``), and the one -I path of every build."""
    here = Path(__file__).resolve().parent.parent  # the package
    for candidate in (here / "kernels", here.parent / "kernels"):
        if (candidate / "core").is_dir():
            return candidate
    raise FileNotFoundError(f"hlbvh_cl: the OpenCL kernels are missing (looked in {here / 'kernels'} "
                            f"and {here.parent / 'kernels'}); reinstall the package")


def kernel_of(module: str) -> str:
    """The kernel file of a host module, by the rule that pairs them: the
    same room and name (``hlbvh_cl.query.rays`` -> ``query/rays.cl``)."""
    room, _, name = module.removeprefix("hlbvh_cl.").rpartition(".")
    return f"{room.replace('.', '/')}/{name}.cl"
