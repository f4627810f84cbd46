"""Device profiles, kernel variants and the probe that chooses them in a child
process (hlbvh_cl.profile, hlbvh_cl.probe)."""
import warnings

import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl import device as device_module
from hlbvh_cl import probe
from hlbvh_cl.device import KernelBuildError, Runtime, select_device
from hlbvh_cl.profile import SAFEST, Profile, Variant, candidates, profile_name, vector_width

CPU, GPU = Profile("cpu"), Profile("gpu")


def names(variants):
    return [v.name for v in variants]


@pytest.mark.parametrize("target, expected", [
    # PyPI's PoCL 3.0 on a Zen 4: 16-wide vectors reported, znver3 (AVX2) compiled
    ({"x86": True, "avx": True, "avx512": False, "reported_width": 16},
     ["packet8", "packet1", "packet1-plain"]),
    ({"x86": True, "avx": True, "avx512": True, "reported_width": 16},
     ["packet16", "packet8", "packet1", "packet1-plain"]),
    ({"x86": True, "avx": False, "avx512": False, "reported_width": 4}, ["packet1", "packet1-plain"]),
    # a SPIR front end (Intel's CPU runtime) reveals no target: its report counts
    ({"x86": False, "avx": False, "avx512": False, "reported_width": 8},
     ["packet8", "packet1", "packet1-plain"]),
    ({"x86": False, "avx": False, "avx512": False, "reported_width": 16},
     ["packet16", "packet8", "packet1", "packet1-plain"]),
])
def test_cpu_candidates_follow_the_compilers_real_target(target, expected):
    assert names(candidates(CPU, target)) == expected
    assert vector_width(target) >= max(v.packet_size for v in candidates(CPU, target))


def test_gpu_profile_traces_one_ray_per_work_item():
    wide = {"x86": True, "avx": True, "avx512": True, "reported_width": 16}
    assert names(candidates(GPU, wide)) == ["packet1", "packet1-plain"]
    assert candidates(GPU, wide)[-1] == SAFEST == Variant.parse("packet1-plain")
    assert Variant.parse("packet8") == Variant(8) and SAFEST.defines == {"PLAIN_OPENCL": 1}
    with pytest.raises(ValueError, match="not a kernel variant"):
        Variant.parse("packet8-fast")


def test_profile_comes_from_the_device_type_or_the_environment(monkeypatch):
    monkeypatch.delenv("HLBVH_CL_PROFILE", raising=False)
    assert profile_name("cpu") == "cpu"
    assert profile_name("gpu") == profile_name("accelerator") == "gpu"
    monkeypatch.setenv("HLBVH_CL_PROFILE", "GPU")
    assert profile_name("cpu") == "gpu"
    monkeypatch.setenv("HLBVH_CL_PROFILE", "fpga")
    with pytest.raises(ValueError, match="HLBVH_CL_PROFILE='fpga' is not a profile"):
        profile_name("cpu")


def test_default_device_is_never_a_simulator_and_always_works(monkeypatch):
    monkeypatch.delenv("HLBVH_CL_DEVICE", raising=False)
    chosen = select_device()
    assert not chosen.simulator and chosen.problem is None
    usable = [d for d in hlbvh_cl.devices() if d.skipped_because is None]
    gpus = [d for d in usable if d.type == "gpu"]
    if gpus:
        assert chosen.type == "gpu"
    else:  # the CPU runtime that traced fastest in its probe
        cpus = [d for d in usable if d.type == "cpu"]
        assert chosen.verdict.mrays_per_s == max(d.verdict.mrays_per_s for d in cpus)
    for d in hlbvh_cl.devices():
        if d.simulator:
            assert "simulator" in d.skipped_because


@pytest.fixture
def fresh_probes(tmp_path, monkeypatch, suite_device):
    """The suite's device, its verdicts in an empty folder of this test's own
    (compiled programs stay in the usual caches)."""
    monkeypatch.setattr(probe, "cache_root", lambda: tmp_path)
    monkeypatch.setattr(probe, "_memory", {})
    monkeypatch.setattr(probe, "_warned", set())
    return suite_device


def test_a_variant_that_crashes_the_compiler_falls_back_with_one_warning(fresh_probes,
                                                                         monkeypatch):
    device = fresh_probes
    best = device.verdict.chosen  # probed in a child, cached in tmp_path
    assert best is not None and list(probe.cache_root().glob("probes/*.json"))
    monkeypatch.setattr(probe, "_memory", {})
    for path in probe.cache_root().glob("probes/*.json"):
        path.unlink()
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", f"{best.name}:abort")
    verdict = device.verdict  # the child aborts as LLVM does; this process goes on
    assert verdict.chosen is not None and verdict.chosen != best
    (failed, reason), = verdict.failures
    assert failed == best and "injected" in reason and "signal 6" in reason
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rt = Runtime(device)
    assert rt.variant == verdict.chosen
    messages = [str(w.message) for w in caught if "hlbvh_cl" in str(w.message)]
    assert len(messages) == 1 and f"cannot run kernel variant {best.name}" in messages[0]
    assert "\n" not in messages[0]


def test_a_hanging_variant_times_out(fresh_probes, monkeypatch):
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", "packet8:hang")
    monkeypatch.setenv("HLBVH_CL_PROBE_TIMEOUT", "5")
    reason = probe.usable(fresh_probes, CPU, Variant(8))
    assert reason == "timed out after 5 s"


def test_a_device_where_no_variant_runs_raises_kernel_build_error(fresh_probes, monkeypatch):
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", "*:abort")
    device = fresh_probes
    assert device.problem is not None and "packet1-plain" in device.problem
    with pytest.raises(KernelBuildError, match=f"no kernel variant runs on {device.id}"):
        Runtime(device)
    with pytest.raises(RuntimeError, match="no OpenCL device here can run"):
        monkeypatch.setattr(device_module, "_devices_cache", [device])
        monkeypatch.delenv("HLBVH_CL_DEVICE", raising=False)
        select_device()


def test_a_requested_packet_the_device_cannot_run_gives_way(fresh_probes, monkeypatch):
    from hlbvh_cl.query import RayQuery
    device = fresh_probes
    rt = Runtime(device)
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", "packet16:abort")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        query = RayQuery(rt, packet_size=16)
    assert query.packet_size < 16
    assert any("cannot run kernel variant packet16" in str(w.message) for w in caught)


def test_every_profile_gives_the_same_hits(monkeypatch, suite_device):
    """Each profile forced on the suite's device traces what the other does
    (the GPU profile: one ray per work-item, device copies, GPU group sizes)."""
    from shapes import grid_mesh
    mesh = grid_mesh(6)
    rng = np.random.default_rng(3)
    origins = rng.uniform(-1, 7, (500, 3)) + [0, 0, 3]
    directions = rng.normal(size=(500, 3)) + [0, 0, -2]
    results = {}
    for name in ("cpu", "gpu"):
        monkeypatch.setenv("HLBVH_CL_PROFILE", name)
        scene = hlbvh_cl.Scene([mesh], device=suite_device)
        assert scene._runtime.profile.name == name
        results[name] = scene.intersect(origins, directions)
    assert results["gpu"].hit.any()
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(results["cpu"], field), getattr(results["gpu"], field))
