"""Device profiles and kernel variants: what each kind of device is given.

A *profile* is the shape of the work: ``cpu`` traces a packet of coherent rays
per work-item in vector lanes, prefetches, and lets the kernels read numpy
arrays in place; ``gpu`` traces one ray per work-item (SIMT lanes already run
neighbouring rays together) in larger work-groups, with device copies.  It is
chosen from the device's type and can be forced with ``HLBVH_CL_PROFILE`` on
any device, so that the GPU path is tested where there is no GPU.

A *variant* is how the kernels are compiled within a profile: the packet width
and whether compiler builtins may be used (kernels/core/portable.h, HAS_BUILTIN).  The
candidates are listed fastest first and end in the safest one, one ray per
work-item in plain OpenCL C; hlbvh_cl.device.probe tries them in a child process and
keeps the first that builds, runs and gives the right hits.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

PROFILES = ("cpu", "gpu")

#: Rays per work-item the traversal kernels can be built for (PACKET_SIZE).
PACKET_SIZES = (1, 8, 16)


@dataclass(frozen=True)
class Variant:
    """How the kernels are compiled: rays per work-item, and builtins or not."""

    packet_size: int
    builtins: bool = True

    @property
    def name(self) -> str:
        return f"packet{self.packet_size}" + ("" if self.builtins else "-plain")

    @property
    def defines(self) -> dict:
        """Defines every program of a runtime with this variant is built with."""
        return {} if self.builtins else {"PLAIN_OPENCL": 1}

    @classmethod
    def parse(cls, name: str) -> Variant:
        base, _, plain = name.partition("-")
        if not base.startswith("packet") or plain not in ("", "plain"):
            raise ValueError(f"not a kernel variant name: {name!r}")
        return cls(int(base[len("packet"):]), builtins=not plain)

    def with_packet(self, packet_size: int) -> Variant:
        return Variant(packet_size, self.builtins)


#: The variant every conforming OpenCL C 1.2 compiler must run.
SAFEST = Variant(1, builtins=False)


@dataclass(frozen=True)
class Profile:
    """The kind of work a device is given (see the module's docstring)."""

    name: str

    @property
    def gpu(self) -> bool:
        return self.name == "gpu"


def profile_name(device_type: str) -> str:
    """``$HLBVH_CL_PROFILE`` when set, else ``cpu`` for CPU devices and ``gpu``
    for every other kind (GPUs, accelerators, simulators)."""
    forced = os.environ.get("HLBVH_CL_PROFILE", "").strip().lower()
    if forced:
        if forced not in PROFILES:
            raise ValueError(f"HLBVH_CL_PROFILE={forced!r} is not a profile; expected one of "
                             f"{', '.join(PROFILES)}")
        return forced
    return "cpu" if device_type == "cpu" else "gpu"


def vector_width(target: dict) -> int:
    """Float lanes of the vector registers the device's compiler targets.

    Read from the compiler's own predefined macros (kernels/device/probe.cl):
    PoCL's Clang defines __AVX512F__ only when it really emits AVX-512, where
    its runtime may report 16-wide vectors for a CPU it compiles for as
    znver3.  Compilers that reveal no target (SPIR front ends such as Intel's
    runtime) fall back to the width the runtime reports."""
    if target.get("avx512"):
        return 16
    if target.get("avx"):
        return 8
    if target.get("x86"):
        return 4
    return int(target.get("reported_width", 1))


def candidates(profile: Profile, target: dict) -> tuple[Variant, ...]:
    """Variants to try, fastest first, ending in SAFEST.  On CPUs a packet is
    one native float vector wide (a wider one spills); GPUs trace one ray per
    work-item."""
    packets = [1]
    if not profile.gpu:
        width = vector_width(target)
        packets = [p for p in sorted(PACKET_SIZES, reverse=True) if p > 1 and p <= width] + [1]
    variants = [Variant(p) for p in packets] if target.get("builtins", True) else []
    return tuple(variants) + (SAFEST,)
