"""Which device a spec names: the rules of ``select_device``, as plain
functions of a device list, so that they can be tested on any host.

A spec is tried as, in order:

1. an index (``0``, ``"1"``) into the list ``devices()`` gives;
2. a device id (``"pocl:1"``);
3. a runtime key, the part of an id before the colon (``"pocl"``,
   ``"intel"``, ``"nvidia"``, ``"amd"``, ``"oclgrind"``): that runtime's
   devices, chosen by platform and never by the device's name.  PoCL names
   its CPU device after the processor ("pthread-Intel(R) Xeon(R)",
   "pthread-AMD EPYC"), so a name match would let ``"intel"`` or ``"amd"``
   pick PoCL;
4. a device type (``"cpu"``, ``"gpu"``, ``"accelerator"``): the devices of
   that type, simulators left out (Oclgrind reports itself as a GPU);
5. a substring of a device's name or platform, as a last resort, and only
   when every device it matches belongs to one runtime: otherwise it is an
   error that lists the candidates.

Where a rule leaves several devices (two PoCL builds, a GPU and a CPU of
one vendor), the best that runs the kernels is taken (:func:`best`).
"""
from __future__ import annotations

#: The runtime keys of the platforms known by name (hlbvh_cl.device.runtime's
#: _VENDORS, plus the simulator).  A key stays a runtime key when its
#: runtime is absent: ``"amd"`` on an AMD host without AMD's runtime is an
#: error, not PoCL's "pthread-AMD EPYC".
KNOWN_RUNTIMES = ("pocl", "intel", "nvidia", "amd", "apple", "rusticl", "clover", "arm",
                  "qualcomm", "oclgrind")

#: Device types, in the order the default choice prefers them.
TYPES = ("gpu", "cpu", "accelerator", "other")

#: Runtimes, in the order the choice among devices of one type prefers them
#: (best): a GPU's vendor before the runtimes that drive other vendors'
#: GPUs too; on a CPU, PoCL (the runtime the suite tests) before Intel's.
#: Unlisted runtimes come after these.
RUNTIME_ORDER = ("nvidia", "amd", "apple", "arm", "qualcomm", "pocl", "intel", "rusticl",
                 "clover")


def runtime_key(device) -> str:
    """The runtime part of a device's id: ``"pocl"`` for ``"pocl:1"``."""
    return device.id.partition(":")[0]


def describe(devices) -> str:
    return "; ".join(str(d) for d in devices) or "none"


def best(candidates):
    """The device to take among ``candidates``: one whose kernels run, of
    the type TYPES prefers, then one that runs the first kernel variant its
    profile names over one that fell back to another (PyPI's PoCL 3.0 on a
    Zen 4 host runs only packet1, beside Debian's PoCL that runs packet16),
    then of the runtime RUNTIME_ORDER prefers, and only then the fastest
    camera rays in its probe (two builds of one runtime); None when none
    runs.  Probes only the candidates given.  The probe's speed, a second
    on a small scene, ranks runtimes either way on a shared machine (on one
    2-core Zen 4 host, PoCL 29.9 against Intel's 14.5 Mrays/s in one probe,
    12.9 against 15.4 in the next, under load): the default device changed
    from one run to the next."""
    working = [d for d in candidates if d.problem is None]
    if not working:
        return None
    return max(working, key=lambda d: (-_type_rank(d.type), not d.verdict.failures,
                                       -_runtime_rank(d), d.verdict.mrays_per_s or 0.0))


def _type_rank(device_type: str) -> int:
    return TYPES.index(device_type) if device_type in TYPES else len(TYPES)


def _runtime_rank(device) -> int:
    key = runtime_key(device)
    return RUNTIME_ORDER.index(key) if key in RUNTIME_ORDER else len(RUNTIME_ORDER)


def choose(spec, available, source: str, missing=()):
    """The device of ``available`` that ``spec`` names (see the module's
    docstring); ``missing`` lists runtimes found installed but not listed,
    with why, for the errors.  Raises ValueError or TypeError with the
    devices present when no device, or more than one runtime, fits."""
    if isinstance(spec, bool) or not isinstance(spec, (int, str)):
        raise TypeError(f"{source} must be a device id, an index, a runtime, a device type or a "
                        f"name substring, got {type(spec).__name__}")
    listing = f"present: {describe(available)}"
    why_missing = "".join(f"; not listed: {note}" for note in missing)
    if isinstance(spec, int):
        if not 0 <= spec < len(available):
            raise ValueError(f"{source}={spec} is out of range: {len(available)} device(s); "
                             f"{listing}")
        return available[spec]
    text = spec.strip().lower()
    if text.isdigit():
        return choose(int(text), available, source, missing)
    if not text:
        raise ValueError(f"{source} is empty; {listing}")
    for d in available:
        if d.id == text:
            return d
    if ":" in text:
        raise ValueError(f"{source}={spec!r} is no device id here; {listing}{why_missing}")

    runtimes = {runtime_key(d) for d in available}
    if text in runtimes or text in KNOWN_RUNTIMES:
        of_runtime = [d for d in available if runtime_key(d) == text]
        if not of_runtime:
            raise ValueError(f"{source}={spec!r}: no device of the {text!r} runtime is listed; "
                             f"{listing}{why_missing}")
        return _take(of_runtime, spec, source, f"of the {text!r} runtime")

    if text in TYPES:
        of_type = [d for d in available if d.type == text and not d.simulator]
        if not of_type:
            simulators = [d.id for d in available if d.type == text and d.simulator]
            also = (f" ({', '.join(simulators)}: a simulator, used only when named by id)"
                    if simulators else "")
            raise ValueError(f"{source}={spec!r}: no {text} device is listed{also}; "
                             f"{listing}{why_missing}")
        return _take(of_type, spec, source, f"of type {text}")

    named = [d for d in available if text in d.name.lower() or text in d.platform.lower()]
    if not named:
        raise ValueError(f"{source}={spec!r} matches no OpenCL device (a device id, an index, a "
                         f"runtime such as {', '.join(sorted(runtimes)) or 'pocl'}, a type such "
                         f"as cpu or gpu, or a name substring); {listing}{why_missing}")
    keys = sorted({runtime_key(d) for d in named})
    if len(keys) > 1:
        raise ValueError(f"{source}={spec!r} is ambiguous: it names devices of {len(keys)} "
                         f"runtimes ({describe(named)}); name one by its id "
                         f"({source}={named[0].id!r}) or its runtime ({source}={keys[0]!r})")
    return _take(named, spec, source, f"named {text!r}")


def _take(candidates, spec, source: str, what: str):
    if len(candidates) == 1:
        return candidates[0]  # its runtime says why, if its kernels fail
    chosen = best(candidates)
    if chosen is None:
        problems = "; ".join(f"{d.id}: {d.problem}" for d in candidates)
        raise ValueError(f"{source}={spec!r}: no device {what} runs the kernels ({problems})")
    return chosen


def default(available):
    """The device taken when none is named: the best working device of the
    first type in TYPES that has one (a GPU before a CPU), never a simulator;
    None when no device runs the kernels."""
    for wanted in TYPES:
        chosen = best([d for d in available if d.type == wanted and not d.simulator])
        if chosen is not None:
            return chosen
    return None
