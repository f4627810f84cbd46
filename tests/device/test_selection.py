"""The rules by which a device spec picks a device (hlbvh_cl.device.selection), on
fake device lists, so that they hold whatever CPU runs the suite: PoCL names
its device after the processor ("pthread-Intel(R) Xeon(R)", "pthread-AMD
EPYC"), so a rule that looked at names would pick PoCL for "intel" or "amd"
on one host and not on another."""
from dataclasses import dataclass

import pytest

from hlbvh_cl.device.selection import choose, default


@dataclass(frozen=True)
class Verdict:
    failures: tuple = ()
    mrays_per_s: float | None = 10.0


@dataclass(frozen=True)
class Fake:
    """What selection reads of a hlbvh_cl.Device."""
    id: str
    name: str
    platform: str
    type: str = "cpu"
    problem: str | None = None
    mrays: float = 10.0
    fell_back: bool = False  # its probe failed its first kernel variant

    @property
    def simulator(self) -> bool:
        return "oclgrind" in self.platform.lower()

    @property
    def verdict(self) -> Verdict:
        failures = (("packet8", "LLVM ERROR (killed by signal 6)"),) if self.fell_back else ()
        return Verdict(failures=failures, mrays_per_s=self.mrays)

    def __str__(self) -> str:
        return f"{self.id} ({self.type}) {self.name} [{self.platform}]"


POCL = "Portable Computing Language"
INTEL_CPU = "Intel(R) OpenCL"
XEON = "Intel(R) Xeon(R) Platinum 8481C"
EPYC = "AMD EPYC 9R14"


def intel_host(intel_mrays=8.0, pocl_mrays=12.0):
    """An Intel Xeon with Intel's runtime, PyPI's PoCL and Oclgrind; PoCL the
    faster in its probe, as on the machine where "intel" once gave PoCL."""
    return [Fake("intel:0", XEON, INTEL_CPU, mrays=intel_mrays),
            Fake("pocl:0", f"pthread-{XEON}", POCL, mrays=pocl_mrays),
            Fake("oclgrind:0", "Oclgrind Simulator", "Oclgrind", type="gpu")]


def amd_host():
    """An AMD EPYC with Intel's CPU runtime (it runs on AMD too), two PoCL
    builds (PyPI's and Debian's), an NVIDIA GPU and Oclgrind."""
    return [Fake("intel:0", EPYC, INTEL_CPU, mrays=8.0),
            Fake("nvidia:0", "NVIDIA H100 80GB HBM3", "NVIDIA CUDA", type="gpu", mrays=900.0),
            Fake("pocl:0", f"pthread-{EPYC}", POCL, problem="unknown target CPU 'generic'"),
            Fake("pocl:1", f"cpu-{EPYC}", POCL, mrays=15.0),
            Fake("oclgrind:0", "Oclgrind Simulator", "Oclgrind", type="gpu")]


def ids(devices):
    return [d.id for d in devices]


@pytest.mark.parametrize("intel_mrays, pocl_mrays", [(8.0, 12.0), (12.0, 8.0)])
def test_a_runtime_key_picks_its_platform_never_a_name(intel_mrays, pocl_mrays):
    host = intel_host(intel_mrays, pocl_mrays)
    for spec in ("intel", "INTEL", " intel "):
        assert choose(spec, host, "device").id == "intel:0"
    assert choose("pocl", host, "device").id == "pocl:0"
    assert choose("oclgrind", host, "device").id == "oclgrind:0"  # named: allowed
    amd_gpu = [*amd_host(), Fake("amd:0", "gfx1100", "AMD Accelerated Parallel Processing",
                                 type="gpu")]
    assert choose("amd", amd_gpu, "device").id == "amd:0"


def test_a_runtime_key_with_no_device_says_why_and_never_falls_to_a_name():
    pocl_only = [d for d in intel_host() if not d.id.startswith("intel")]
    missing = ["Intel's CPU runtime (/x/libintelocl.so): undefined symbol: tbb"]
    with pytest.raises(ValueError) as raised:
        choose("intel", pocl_only, "device", missing)
    message = str(raised.value)
    assert "no device of the 'intel' runtime is listed" in message
    assert "not listed: Intel's CPU runtime" in message and "undefined symbol" in message
    assert "present: pocl:0" in message
    # an AMD host without AMD's runtime: "amd" is not PoCL's "pthread-AMD EPYC"
    with pytest.raises(ValueError, match="no device of the 'amd' runtime"):
        choose("amd", [d for d in amd_host() if d.id == "pocl:1"], "device")


def test_a_runtime_with_several_devices_takes_the_best_working_one():
    host = amd_host()
    assert choose("pocl", host, "device").id == "pocl:1"  # pocl:0's kernels fail
    broken = [Fake("pocl:0", "a", POCL, problem="x"), Fake("pocl:1", "b", POCL, problem="y")]
    with pytest.raises(ValueError, match=r"no device of the 'pocl' runtime runs the kernels "
                                         r"\(pocl:0: x; pocl:1: y\)"):
        choose("pocl", broken, "device")
    # one device: taken, and its runtime says why if it fails
    assert choose("pocl", broken[:1], "device").id == "pocl:0"


def test_a_device_type_picks_the_best_working_device_of_that_type():
    host = amd_host()
    assert choose("gpu", host, "device").id == "nvidia:0"
    assert choose("cpu", host, "device").id == "pocl:1"  # pocl:0 fails
    assert choose("CPU", intel_host(12.0, 8.0), "device").id == "pocl:0"  # PoCL first
    assert choose("cpu", [d for d in host if d.id != "pocl:1"], "device").id == "intel:0"
    # Oclgrind reports a GPU, but a type never picks a simulator
    with pytest.raises(ValueError) as raised:
        choose("gpu", intel_host(), "device")
    assert "no gpu device is listed (oclgrind:0: a simulator" in str(raised.value)
    with pytest.raises(ValueError, match="no accelerator device"):
        choose("accelerator", intel_host(), "device")


def test_a_name_matching_several_runtimes_is_an_error_listing_them():
    with pytest.raises(ValueError) as raised:
        choose("xeon", intel_host(), "HLBVH_CL_DEVICE")
    message = str(raised.value)
    assert "HLBVH_CL_DEVICE='xeon' is ambiguous: it names devices of 2 runtimes" in message
    assert "intel:0 (cpu)" in message and "pocl:0 (cpu)" in message
    with pytest.raises(ValueError, match="ambiguous"):
        choose("epyc", amd_host(), "device")


def test_a_name_within_one_runtime_is_a_last_resort():
    assert choose("h100", amd_host(), "device").id == "nvidia:0"
    assert choose("portable", amd_host(), "device").id == "pocl:1"  # a platform name
    assert choose("simulator", intel_host(), "device").id == "oclgrind:0"
    with pytest.raises(ValueError, match="matches no OpenCL device"):
        choose("no-such-gpu", amd_host(), "device")


def test_ids_and_indices():
    host = amd_host()
    assert choose("pocl:0", host, "device").id == "pocl:0"  # an id is exact, working or not
    assert choose(2, host, "device").id == "pocl:0"
    assert choose("3", host, "device").id == "pocl:1"
    with pytest.raises(ValueError, match="out of range"):
        choose(9, host, "device")
    with pytest.raises(ValueError, match="'pocl:7' is no device id here"):
        choose("pocl:7", host, "device")
    with pytest.raises(TypeError, match="device must be a device id"):
        choose(1.5, host, "device")
    with pytest.raises(TypeError):
        choose(True, host, "device")
    with pytest.raises(ValueError, match="device is empty"):
        choose("  ", host, "device")


def test_the_default_prefers_a_working_gpu_then_pocl_never_a_simulator():
    assert default(amd_host()).id == "nvidia:0"
    assert default(intel_host(8.0, 12.0)).id == "pocl:0"
    only_simulator = [d for d in intel_host() if d.simulator]
    assert default(only_simulator) is None
    assert default([Fake("pocl:0", "x", POCL, problem="fails")]) is None


@pytest.mark.parametrize("intel_mrays", [5.0, 30.0])
def test_the_probes_speed_does_not_rank_runtimes(intel_mrays):
    """The probe's speed, a second on a small scene, ranked PoCL and Intel's
    runtime either way from one run to the next on a shared 2-core host
    (29.9 against 14.5 Mrays/s, then 12.9 against 15.4): the default
    device changed with it."""
    assert default(intel_host(intel_mrays, 12.0)).id == "pocl:0"
    assert choose("cpu", intel_host(intel_mrays, 12.0), "device").id == "pocl:0"
    gpus = [Fake("pocl:0", "NVIDIA H100", POCL, type="gpu", mrays=90.0),
            Fake("nvidia:0", "NVIDIA H100", "NVIDIA CUDA", type="gpu", mrays=60.0)]
    assert default(gpus).id == "nvidia:0"  # the vendor's, before PoCL's CUDA driver
    # between two builds of one runtime, both running their first variant,
    # the probe decides
    builds = [Fake("pocl:0", "cpu", POCL, mrays=8.0), Fake("pocl:1", "cpu", POCL, mrays=9.0)]
    assert default(builds).id == "pocl:1"


@pytest.mark.parametrize("fallback_mrays", [5.0, 15.0])
def test_a_device_that_runs_its_first_variant_beats_one_that_fell_back(fallback_mrays):
    """A Zen 4 host: PyPI's PoCL runs only packet1 there, Debian's packet16; the
    probes' speeds on a shared 2-core machine ranked them either way."""
    host = [Fake("pocl:0", f"pthread-{EPYC}", POCL, mrays=10.0),
            Fake("pocl:1", f"pthread-{EPYC}", POCL, mrays=fallback_mrays, fell_back=True),
            Fake("intel:0", EPYC, INTEL_CPU, mrays=8.0)]
    assert choose("pocl", host, "device").id == "pocl:0"
    assert default(host).id == "pocl:0"
    assert choose("pocl", host[1:], "device").id == "pocl:1"  # the one there is


@pytest.mark.parametrize("value", ["abc", "-1", "0", "nan", "inf"])
def test_a_bad_probe_timeout_names_the_variable(value, monkeypatch):
    """HLBVH_CL_PROBE_TIMEOUT was read by float() alone: "abc" gave
    "could not convert string to float", and -1 failed every variant as a
    timeout."""
    from hlbvh_cl.device import probe
    monkeypatch.setenv("HLBVH_CL_PROBE_TIMEOUT", value)
    with pytest.raises(ValueError, match=rf"HLBVH_CL_PROBE_TIMEOUT='{value}': expected the "
                                         "seconds a device probe may take, a number above 0"):
        probe.timeout_s()
    monkeypatch.setenv("HLBVH_CL_PROBE_TIMEOUT", "12.5")
    assert probe.timeout_s() == 12.5
