"""Devices: listing and selection, program caching and build errors; the
profiles and kernel variants that the probe chooses in a child process
(hlbvh_cl.device.profile, hlbvh_cl.device.probe); and hlbvh_cl/core/layout.py against
kernels/core/portable.h on every device.  test_targets.py reruns the correctness
modules on every other device and profile."""
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

import hlbvh_cl
from hlbvh_cl.device import discovery as discovery_module
from hlbvh_cl.device import runtime as device_module
from hlbvh_cl.core import layout
from hlbvh_cl.device import probe
from hlbvh_cl.device.discovery import devices, select_device, write_vendors
from hlbvh_cl.device.runtime import KernelBuildError, Runtime, quiet_build, runtime
from hlbvh_cl.core.paths import kernel_dir
from hlbvh_cl.render.random import salts8
from hlbvh_cl.device.profile import SAFEST, Profile, Variant, candidates, profile_name, vector_width

import built


# -- listing, selection, programs ---------------------------------------------------

def test_devices_have_stable_short_ids(suite_device):
    found = hlbvh_cl.devices()
    assert found, "the suite needs an OpenCL device"
    ids = [d.id for d in found]
    assert len(set(ids)) == len(ids)
    for i, d in enumerate(found):
        vendor, k = d.id.split(":")
        assert vendor.isalnum() and vendor == vendor.lower() and int(k) >= 0
        assert d.index == i and d.type in ("cpu", "gpu", "accelerator", "other")
        assert d.platform and d.name
    assert suite_device in found and suite_device.problem is None
    # simulators come last: device=0 picks a real device where there is one
    kinds = [d.simulator for d in found]
    assert kinds == sorted(kinds)


def test_selection_by_id_index_substring_and_environment(monkeypatch, suite_device):
    found = hlbvh_cl.devices()
    first = found[0]
    assert select_device(first.id) == first
    assert select_device(0) == first
    assert select_device(str(0)) == first
    vendor = suite_device.id.split(":")[0]
    named = select_device(vendor.upper())  # case-insensitive substring, first that works
    assert vendor in f"{named.id} {named.name} {named.platform}".lower() and named.problem is None
    monkeypatch.setenv("HLBVH_CL_DEVICE", named.id)
    assert select_device() == named
    assert select_device(first.id) == first  # the argument wins over the environment
    monkeypatch.setenv("HLBVH_CL_DEVICE", "nothing-like-this")
    with pytest.raises(ValueError, match="HLBVH_CL_DEVICE='nothing-like-this' matches no"):
        select_device()


def test_bad_device_arguments():
    with pytest.raises(ValueError, match="out of range"):
        select_device(999)
    with pytest.raises(TypeError, match="device must be"):
        select_device(1.5)
    with pytest.raises(ValueError, match="matches no OpenCL device"):
        select_device("no-such-gpu")


def test_no_platform_says_how_to_install(monkeypatch):
    monkeypatch.setattr(discovery_module, "_devices_cache", [])
    with pytest.raises(RuntimeError, match="pip install pocl-binary-distribution"):
        select_device()


@pytest.mark.skipif(not (Path(sys.prefix) / "lib" / "libintelocl.so").is_file(),
                    reason="intel-opencl-rt is not installed")
def test_intel_cpu_runtime_is_found_without_user_icd_files():
    if "OCL_ICD_VENDORS" in os.environ and "hlbvh_cl" not in os.environ["OCL_ICD_VENDORS"]:
        pytest.skip("the user's own OCL_ICD_VENDORS is in force")
    assert any(d.id.startswith("intel:") for d in hlbvh_cl.devices())


def test_the_vendors_folder_follows_the_system_s(tmp_path):
    """The copies of the system's .icd files follow it: one added is copied,
    one changed is rewritten, one whose runtime was uninstalled goes (the
    ICD loader would try its missing library in every process)."""
    system, folder, lib = tmp_path / "vendors", tmp_path / "icd", Path("/x/libintelocl.so")
    system.mkdir()
    (system / "pocl.icd").write_text("libpocl.so.2\n")
    (system / "nvidia.icd").write_text("libnvidia-opencl.so.1\n")
    write_vendors(folder, lib, system)
    assert sorted(p.name for p in folder.glob("*.icd")) == [
        "intel-cpu-hlbvh_cl.icd", "nvidia.icd", "pocl.icd"]
    (system / "pocl.icd").unlink()
    (system / "nvidia.icd").write_text("/opt/libnvidia-opencl.so.1\n")
    write_vendors(folder, lib, system)
    assert sorted(p.name for p in folder.glob("*.icd")) == ["intel-cpu-hlbvh_cl.icd", "nvidia.icd"]
    assert (folder / "nvidia.icd").read_text() == "/opt/libnvidia-opencl.so.1\n"
    assert (folder / "intel-cpu-hlbvh_cl.icd").read_text() == f"{lib}\n"
    write_vendors(folder, lib, tmp_path / "none")  # no system folder: Intel's alone
    assert [p.name for p in folder.glob("*.icd")] == ["intel-cpu-hlbvh_cl.icd"]


def test_programs_are_built_once_and_cached():
    rt = runtime()
    defines = {"STRIDED_SLICES": 0, "FOLD_GROUP": 64}
    assert rt.program("build/bounds.cl", **defines) is rt.program("build/bounds.cl", **defines)
    assert rt.kernel("build/morton.cl", "morton_codes", MORTON_BITS=30) is \
        rt.kernel("build/morton.cl", "morton_codes", MORTON_BITS=30)


def test_a_runtime_builds_from_its_kernel_root(tmp_path):
    """Runtime.kernel_root (bench.ab --in-process): programs and kernels come
    from the folder it names at the time, each folder's cached on its own."""
    rt = Runtime(select_device())  # not the shared runtime: its root stays
    assert rt.kernel_root == kernel_dir()
    ours = rt.kernel("build/morton.cl", "morton_codes", MORTON_BITS=30)
    (tmp_path / "build").mkdir()
    (tmp_path / "build" / "morton.cl").write_text(
        "__kernel void morton_codes(__global int *x) { x[0] = another_root; }\n")
    rt.kernel_root = tmp_path
    with pytest.raises(KernelBuildError, match="morton.cl failed to build") as info:
        rt.kernel("build/morton.cl", "morton_codes", MORTON_BITS=30)
    assert "another_root" in str(info.value)
    rt.kernel_root = kernel_dir()
    assert rt.kernel("build/morton.cl", "morton_codes", MORTON_BITS=30) is ours


def test_threads_asking_for_a_new_kernel_at_once_get_one_object():
    """Runtime.kernel's cache: threads that create the same kernel at once
    all get the one stored (before, each kept its own, and largest_group's
    cache gained an entry per copy)."""
    import threading
    rt = runtime()
    barrier, got = threading.Barrier(4), [None] * 4

    def ask(k):
        barrier.wait()
        got[k] = rt.kernel("parallel/scan.cl", "scan_reduce_tiles", SCAN_GROUP_SIZE=8)

    threads = [threading.Thread(target=ask, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert len({id(kernel) for kernel in got}) == 1
    assert rt.largest_group(got[0]) == rt.largest_group(got[0]) >= 1


def test_compile_error_shows_the_build_log(tmp_path, monkeypatch):
    (tmp_path / "broken.cl").write_text("__kernel void f(__global int *x) { x[0] = nope; }\n")
    monkeypatch.setattr(device_module, "kernel_dir", lambda: tmp_path)
    rt = Runtime(select_device())
    with pytest.raises(KernelBuildError, match="broken.cl failed to build") as info:
        rt.program("broken.cl")
    assert "nope" in str(info.value)  # the compiler's own message is in the log


def test_a_build_log_is_logged_not_warned(tmp_path, monkeypatch, caplog):
    """pyopencl warns (CompilerWarning) on any non-empty build log, which
    Intel's runtime writes for every build: the library keeps it off its
    users' screens and on the "hlbvh_cl" logger at DEBUG."""
    # A unique comment: pyopencl's binary cache would give a built program
    # back without its source build's log.
    (tmp_path / "noted.cl").write_text(f"// {tmp_path}\n#warning hlbvh_cl test note\n"
                                       "__kernel void f(__global int *x) { x[0] = 1; }\n")
    monkeypatch.setattr(device_module, "kernel_dir", lambda: tmp_path)
    rt = Runtime(select_device())
    with warnings.catch_warnings(record=True) as caught, caplog.at_level("DEBUG", "hlbvh_cl"):
        warnings.simplefilter("always")
        rt.program("noted.cl")
    assert [str(w.message) for w in caught] == []
    assert "hlbvh_cl test note" in caplog.text


def test_the_traversal_kernels_compile_without_warnings(monkeypatch, caplog):
    """The programs a flat and an instanced scene's queries build (the
    count's widest packets among them) compile without a warning about their source.  PoCL prints every
    warning on the process's stderr (clang's -Wpsabi note at each 16-lane
    helper on an AVX2 target, before packet_lanes.h silenced it).  The
    programs are built again with an extra define, so that neither
    pyopencl's nor PoCL's binary cache hands back a program without its log."""
    import uuid
    from shapes import grid_mesh
    requested = []
    real, real_kernel = Runtime.program, Runtime.kernel
    monkeypatch.setattr(Runtime, "program", lambda self, filename, **defines: (
        requested.append((self, filename, defines)), real(self, filename, **defines))[1])
    # kernels come from Runtime.kernel's cache without a call to program
    # where an earlier test of this process built them
    monkeypatch.setattr(Runtime, "kernel", lambda self, filename, name, **defines: (
        requested.append((self, filename, defines)),
        real_kernel(self, filename, name, **defines))[1])
    scene = hlbvh_cl.Scene(grid_mesh(6))
    origins = np.random.default_rng(5).uniform(-1, 2, (2048, 3)).astype(np.float32)
    scene.count_intersections(origins, np.float32([0.5, 0.5, 0.0]) - origins)
    scene.intersect(origins, np.float32([0.5, 0.5, 0.0]) - origins)
    scene.closest_points(origins)
    scene.winding_number(origins)
    placed = hlbvh_cl.Scene([grid_mesh(6)], instances=[(0, np.eye(3, 4))])
    placed.closest_points(origins)
    placed.winding_number(origins)
    assert requested
    nonce = uuid.uuid4().hex[:12]
    with caplog.at_level("DEBUG", "hlbvh_cl"):
        for rt, filename, defines in {(rt, f, tuple(sorted(d.items()))) for rt, f, d in requested}:
            real(rt, filename, **dict(defines), TEST_NONCE=f"0x{nonce}")
    # every compiler warning but Intel's note that it leaves a packet kernel
    # unvectorised, as its vec_type_hint asks ('warning: kernel "name": ...';
    # PoCL names the main .cl file by a temporary copy's path)
    warned = [line for line in caplog.text.splitlines()
              if "warning:" in line and 'warning: kernel "' not in line]
    assert warned == [], warned[:5]


@pytest.mark.skipif(not (Path(sys.prefix) / "lib" / "libintelocl.so").is_file(),
                    reason="intel-opencl-rt is not installed")
def test_a_runtime_that_cannot_be_registered_says_why(tmp_path):
    """A user's OCL_ICD_VENDORS folder without Intel's .icd hides the runtime:
    devices() warns and the error for device='intel' names the reason."""
    import subprocess
    child = ("import warnings, hlbvh_cl\n"
             "from hlbvh_cl.device.runtime import select_device\n"
             "with warnings.catch_warnings(record=True) as caught:\n"
             "    warnings.simplefilter('always')\n"
             "    hlbvh_cl.devices()\n"
             "print([str(w.message) for w in caught])\n"
             "try:\n"
             "    select_device('intel')\n"
             "except ValueError as error:\n"
             "    print(error)\n")
    env = {**os.environ, "OCL_ICD_VENDORS": str(tmp_path)}
    env.pop("HLBVH_CL_DEVICE", None)
    done = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True,
                          timeout=120)
    warned, error = done.stdout.strip().splitlines()[-2:]
    assert "Intel's CPU runtime" in warned and f"OCL_ICD_VENDORS={tmp_path}" in warned
    # by platform, never by name: PoCL's "pthread-Intel(R) Xeon(R)" is not Intel's runtime
    assert "no device of the 'intel' runtime is listed" in error
    assert "not listed: Intel's CPU runtime" in error


def test_a_listed_runtime_whose_library_cannot_load_is_named(tmp_path):
    """An .icd file whose library is missing: the ICD loader skips it
    without a word; devices() and the errors name it, with the loader's."""
    import subprocess
    (tmp_path / "gone.icd").write_text("/nowhere/libgone-opencl.so\n")
    child = ("import warnings, hlbvh_cl\n"
             "with warnings.catch_warnings(record=True) as caught:\n"
             "    warnings.simplefilter('always')\n"
             "    hlbvh_cl.devices()\n"
             "print([str(w.message) for w in caught if 'gone' in str(w.message)])\n"
             "try:\n"
             "    hlbvh_cl.device.discovery.select_device('gone')\n"
             "except (ValueError, RuntimeError) as error:\n"
             "    print(error)\n")
    env = {**os.environ, "OCL_ICD_VENDORS": str(tmp_path)}
    env.pop("HLBVH_CL_DEVICE", None)
    done = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True,
                          timeout=120)
    warned, error = done.stdout.strip().splitlines()[-2:]
    expected = (f"the runtime of {tmp_path / 'gone.icd'} (/nowhere/libgone-opencl.so) fails to "
                "load: /nowhere/libgone-opencl.so: cannot open shared object file")
    assert expected in warned and expected in error


@pytest.mark.skipif(not (Path(sys.prefix) / "lib" / "libintelocl.so").is_file(),
                    reason="intel-opencl-rt is not installed")
def test_a_runtime_that_fails_to_load_is_named_with_the_loaders_words():
    """Open3D bundles an older oneTBB: imported first, it keeps Intel's
    runtime from loading.  devices() says so, with the loader's message and
    the remedy, and device='intel' is an error that names it, never PoCL;
    listing the devices before importing Open3D keeps the runtime, and both
    then answer rays in one process (docs/devices.md, "Import order")."""
    pytest.importorskip("open3d")
    import subprocess
    child = ("import sys, warnings\n"
             "if sys.argv[1] == 'open3d first': import open3d\n"
             "import hlbvh_cl\n"
             "with warnings.catch_warnings(record=True) as caught:\n"
             "    warnings.simplefilter('always')\n"
             "    print([d.id for d in hlbvh_cl.devices()])\n"
             "if sys.argv[1] == 'open3d last':\n"
             "    import numpy as np, open3d as o3d\n"
             "    hits = o3d.t.geometry.RaycastingScene()\n"
             "    tensor = o3d.core.Tensor\n"
             "    hits.add_triangles(tensor(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]])),\n"
             "                       tensor(np.uint32([[0, 1, 2]])))\n"
             "    ray = tensor(np.float32([[.2, .2, 1, 0, 0, -1]]))\n"
             "    assert abs(hits.cast_rays(ray)['t_hit'].numpy()[0] - 1) < 1e-6\n"
             "    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]],\n"
             "                                          [[0, 1, 2]])], device='intel')\n"
             "    assert scene.intersect([.2, .2, 1], [[0, 0, -1]]).t == 1\n"
             "print([str(w.message) for w in caught])\n"
             "try:\n"
             "    print(hlbvh_cl.device.discovery.select_device('intel').id)\n"
             "except ValueError as error:\n"
             "    print(error)\n")
    env = {k: v for k, v in os.environ.items() if k not in ("OCL_ICD_VENDORS", "HLBVH_CL_DEVICE")}
    runs = {}
    for order in ("open3d first", "open3d last"):
        done = subprocess.run([sys.executable, "-c", child, order], env=env, capture_output=True,
                              text=True, timeout=300)
        runs[order] = done.stdout.strip().splitlines()[-3:]
        assert done.returncode == 0 and len(runs[order]) == 3, done.stderr[-3000:]
    listed, warned, chosen = runs["open3d last"]
    assert "intel:0" in listed and chosen == "intel:0"
    listed, warned, error = runs["open3d first"]
    if "intel:0" in listed:
        pytest.skip("this Open3D's oneTBB does not keep Intel's runtime from loading")
    assert "libintelocl.so" in warned and "undefined symbol" in warned
    assert "call hlbvh_cl.devices() before importing it" in warned
    assert "no device of the 'intel' runtime is listed" in error and "undefined symbol" in error


def test_importing_changes_nothing_outside_the_package():
    import subprocess
    child = ("import os; before = dict(os.environ); import pyopencl; before = dict(os.environ)\n"
             "import hlbvh_cl; print(dict(os.environ) == before)")
    env = {k: v for k, v in os.environ.items() if k != "OCL_ICD_VENDORS"}
    done = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.stdout.strip() == "True", done.stderr


# -- profiles and variants -------------------------------------------------------------

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
    else:  # a CPU that runs its first variant where one does; PoCL before Intel's runtime
        cpus = [d for d in usable if d.type == "cpu" and d.problem is None]
        full = [d for d in cpus if not d.verdict.failures]
        assert not chosen.verdict.failures or not full
        if any(d.id.startswith("pocl:") for d in full):
            assert chosen.id.startswith("pocl:")
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
    # the injected abort; a variant that fails on its own here (PyPI's PoCL 3.0
    # on a Zen 4 host cannot compile packet8) is listed beside it
    reasons = dict(verdict.failures)
    assert "injected" in reasons[best] and "signal 6" in reasons[best]
    assert all("injected" not in reason for failed, reason in reasons.items() if failed != best)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rt = Runtime(device)
    assert rt.variant == verdict.chosen
    messages = [str(w.message) for w in caught if "hlbvh_cl" in str(w.message)]
    # one warning a failed variant, each one line
    assert len(messages) == len(reasons)
    assert sum(f"cannot run kernel variant {best.name} (" in m for m in messages) == 1
    assert all("\n" not in m for m in messages)


def _saved_verdicts() -> dict:
    """The variants' verdicts in the probe cache on disk."""
    import json
    return {name: result for path in probe.cache_root().glob("probes/*.json")
            for name, result in json.loads(path.read_text())["results"].items()}


def test_a_hanging_variant_times_out(fresh_probes, monkeypatch):
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", "packet8:hang")
    monkeypatch.setenv("HLBVH_CL_PROBE_TIMEOUT", "5")
    reason = probe.usable(fresh_probes, CPU, Variant(8))
    assert reason == "timed out after 5 s"
    # the machine's state, not the variant: this process falls back, the next one probes again
    assert "packet8" not in _saved_verdicts()


def test_a_probe_killed_from_outside_is_not_remembered_but_a_crash_is(fresh_probes,
                                                                       monkeypatch):
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", "packet8:killed")  # as the OOM killer does
    reason = probe.usable(fresh_probes, CPU, Variant(8))
    assert "killed by signal 9" in reason
    assert "packet8" not in _saved_verdicts()
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", "packet16:abort")  # as a crashing compiler does
    reason = probe.usable(fresh_probes, CPU, Variant(16))
    assert "signal 6" in reason
    assert _saved_verdicts()["packet16"]["ok"] is False


def test_a_verdict_printed_after_the_driver_s_remarks_on_their_line_is_read(fresh_probes,
                                                                            monkeypatch):
    """PoCL writes its remarks (POCL_VECTORIZER_REMARKS=1) to the child's
    stdout without a newline, so that the verdict shares their line: it is
    found there.  A child that exits 0 with no verdict says so, and is not
    remembered: such a line once failed every variant for good, as "exit
    code 0"."""
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", f"{SAFEST.name}:noise")
    assert probe.usable(fresh_probes, CPU, SAFEST) is None
    assert _saved_verdicts()[SAFEST.name]["ok"] is True
    for path in probe.cache_root().glob("probes/*.json"):
        path.unlink()
    monkeypatch.setattr(probe, "_memory", {})
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", f"{SAFEST.name}:silent")
    reason = probe.usable(fresh_probes, CPU, SAFEST)
    assert reason is not None and reason.startswith("the probe gave no verdict"), reason
    assert SAFEST.name not in _saved_verdicts()


def test_a_device_where_no_variant_runs_raises_kernel_build_error(fresh_probes, monkeypatch):
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", "*:abort")
    device = fresh_probes
    assert device.problem is not None and "packet1-plain" in device.problem
    with pytest.raises(KernelBuildError, match=f"no kernel variant runs on {device.id}"):
        Runtime(device)
    with pytest.raises(RuntimeError, match="no OpenCL device here can run"):
        monkeypatch.setattr(discovery_module, "_devices_cache", [device])
        monkeypatch.delenv("HLBVH_CL_DEVICE", raising=False)
        select_device()


def test_a_requested_packet_the_device_cannot_run_gives_way(fresh_probes, monkeypatch):
    """On any host: the compiler's target is made to claim AVX-512, as PoCL's
    does on an AVX-512 CPU, so that 16-lane packets are the first candidate
    here too, and their probe aborts as LLVM did on a Zen 4.  The runtime
    falls back, and so does a query that asks for 16 lanes, each in this
    process, which goes on."""
    from hlbvh_cl.query.rays import RayQuery
    device = fresh_probes
    monkeypatch.setattr(probe, "candidates",  # the candidates for a target that claims it
                        lambda profile, target: candidates(profile, {**target, "avx512": True}))
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", "packet16:abort")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rt = Runtime(device)
        query = RayQuery(rt, packet_size=16)
    assert rt.variant.packet_size < 16 and query.packet_size < 16
    messages = [str(w.message) for w in caught if "cannot run kernel variant packet16" in
                str(w.message)]
    assert messages and all("injected" in m for m in messages)
    if not rt.profile.gpu:  # the CPU profile's candidates started at 16 lanes
        assert device.verdict.failures[0][0] == Variant(16)


def test_a_packet_the_runtime_already_runs_is_not_probed_again(fresh_probes, monkeypatch):
    """A query asking for the packet its runtime runs takes it: that variant
    passed its probe when the runtime was made (a fault injected later is
    not reached)."""
    from hlbvh_cl.query.rays import RayQuery
    rt = Runtime(fresh_probes)
    monkeypatch.setenv("HLBVH_CL_PROBE_FAULT", f"{rt.variant.name}:abort")
    assert RayQuery(rt, packet_size=rt.variant.packet_size).packet_size == rt.variant.packet_size


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
        assert built.runtime(scene).profile.name == name
        results[name] = scene.intersect(origins, directions)
    assert results["gpu"].hit.any()
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(results["cpu"], field), getattr(results["gpu"], field))


def test_kernels_a_device_limits_to_small_groups_run_in_them(monkeypatch, suite_device):
    """A kernel may allow fewer work-items per group than the device
    (CL_KERNEL_WORK_GROUP_SIZE, e.g. a GPU kernel heavy in registers): every
    launch keeps within it, and builds, queries and renders answer as with
    full groups.  Here every kernel reports 3 (so groups of 2), in both
    profiles; the sort and scan size their own groups from the same limit."""
    from shapes import grid_mesh
    mesh = grid_mesh(12)
    rng = np.random.default_rng(4)
    origins = rng.uniform(-1, 13, (3000, 3)) + [0, 0, 3]
    directions = rng.normal(size=(3000, 3)) + [0, 0, -2]
    camera = hlbvh_cl.Camera(eye=(6, -4, 8), target=(6, 6, 0))

    def answers():
        monkeypatch.setattr(device_module, "_runtimes", {})  # fresh runtimes
        scene = hlbvh_cl.Scene([mesh], device=suite_device)
        return (scene.intersect(origins, directions).prim_id,
                scene.count_intersections(origins, directions),
                scene.closest_points(origins).distance, scene.stats.sah_cost,
                hlbvh_cl.Renderer(scene).render(camera, 24, 16))
    asked = []
    info = cl.Kernel.get_work_group_info

    def limited(kernel, param, device):
        if param == cl.kernel_work_group_info.WORK_GROUP_SIZE:
            asked.append(kernel.function_name)
            return 3
        return info(kernel, param, device)
    for profile in ("cpu", "gpu"):
        monkeypatch.setenv("HLBVH_CL_PROFILE", profile)
        monkeypatch.setattr(cl.Kernel, "get_work_group_info", info)
        expected = answers()
        enqueue = cl.enqueue_nd_range_kernel
        groups = []

        def recording(queue, kernel, global_size, local_size, *args, **kwargs):
            groups.append(int(np.prod(local_size)) if local_size else 0)
            return enqueue(queue, kernel, global_size, local_size, *args, **kwargs)
        monkeypatch.setattr(cl.Kernel, "get_work_group_info", limited)
        monkeypatch.setattr(cl, "enqueue_nd_range_kernel", recording)
        got = answers()
        monkeypatch.setattr(cl, "enqueue_nd_range_kernel", enqueue)
        assert {"intersect_closest_arrays", "count_hits_arrays", "sum_top_cost"} <= set(asked)
        assert groups and max(groups) <= 2
        prim_id, counts, distance, sah_cost, image = got
        np.testing.assert_array_equal(prim_id, expected[0])
        np.testing.assert_array_equal(counts, expected[1])
        np.testing.assert_array_equal(distance, expected[2])
        assert sah_cost == pytest.approx(expected[3], rel=1e-5)  # summed in another order
        np.testing.assert_array_equal(image, expected[4])


# -- struct layout on every device -----------------------------------------------------

#: Every struct of layout.STRUCTS and each of its fields: (struct, None) is its size.
FIELDS = [(name, field) for name, dtype in layout.STRUCTS.items()
          for field in (None, *dtype.names)]

#: The probe kernel, written from FIELDS so that it covers every field the
#: numpy mirror names (OpenCL C has no offsetof: measure from a real, never
#: dereferenced, pointer).
PROBE = "".join(f'#include "{header}"\n' for header in layout.HEADERS) + \
    "__kernel void struct_layout(__global int *out)\n{\n" + "".join(
    f"    out[{i}] = (int)sizeof({name});\n" if field is None else
    f"    out[{i}] = (int)((__global char *)&((__global {name} *)out)->{field}"
    f" - (__global char *)out);\n"
    for i, (name, field) in enumerate(FIELDS)) + "}\n"


# Oclgrind lacks Clang's builtins: its runtime's first build falls back to
# the plain variant with the one-line warning the fallback tests check
@pytest.mark.filterwarnings("ignore:hlbvh_cl. oclgrind.*cannot run kernel variant:RuntimeWarning")
@pytest.mark.parametrize("device", [d.id for d in devices() if d.problem is None])
def test_struct_layout_matches_device(device):
    rt = runtime(device)
    out = np.full(len(FIELDS), -1, np.int32)
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, out.nbytes)
    program = quiet_build(cl.Program(rt.context, PROBE), ["-I", str(kernel_dir())],
                          rt.device.cl_device)
    rt.run(program.struct_layout, 1, buf, local_size=1)
    cl.enqueue_copy(rt.queue, out, buf)
    expected = [layout.STRUCTS[s].itemsize if f is None else layout.STRUCTS[s].fields[f][1]
                for s, f in FIELDS]
    assert out.tolist() == expected


def test_constants_come_from_the_header():
    text = layout.header_text()
    assert f"#define CLUSTER_BITS {layout.CLUSTER_BITS}" in text
    assert f"#define MAX_LEAF_SIZE {layout.MAX_LEAF_SIZE}" in text
    assert layout.EMPTY_CHILD == -1 and "#define EMPTY_CHILD (-1)" in text
    assert f"#define WIDE_ARITY {layout.WIDE_ARITY}" in text


def test_an_edit_in_any_kernel_room_changes_the_probes_key(tmp_path):
    """The probe's verdicts are keyed by a hash of every kernel source, in
    subfolders too: an edit in kernels/query/walk/ must re-probe."""
    from hlbvh_cl.device.probe import sources_digest
    header = tmp_path / "query" / "walk" / "walk.h"
    header.parent.mkdir(parents=True)
    header.write_text("/* one */")
    (tmp_path / "core").mkdir()
    (tmp_path / "core" / "portable.h").write_text("/* two */")
    before = sources_digest.__wrapped__(tmp_path)
    header.write_text("/* one, edited */")
    edited = sources_digest.__wrapped__(tmp_path)
    assert edited != before
    header.rename(tmp_path / "core" / "walk.h")  # the same text, moved to another room
    assert sources_digest.__wrapped__(tmp_path) != edited


ECHO = """
__kernel void echo(__global uint* out, const int i, const float f, const uint8 s)
{
    out[0] = (uint)i;
    out[1] = as_uint(f);
    out[2] = s.s0; out[3] = s.s1; out[4] = s.s2; out[5] = s.s3;
    out[6] = s.s4; out[7] = s.s5; out[8] = s.s6; out[9] = s.s7;
}
"""


def test_launch_arguments_reach_the_kernel_bit_for_bit_as_their_types_change(suite_device):
    """Runtime.run declares a kernel's scalar types to pyopencl (which then
    packs them in one go) and declares them again when a call's types differ:
    every value arrives with its bits, a uint8 vector (salts8's) included,
    whichever types came before."""
    rt = runtime(suite_device)
    program = quiet_build(cl.Program(rt.context, ECHO), [], rt.device.cl_device)
    kernel = cl.Kernel(program, "echo")
    out = np.zeros(10, np.uint32)
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, out.nbytes)
    salts = salts8(12345, 10)
    calls = [(7, 2.5), (np.int32(-4), np.float32(1e-3)),
             (np.uint32(3_000_000_000), np.float32(-0.0)),  # another type in slot 1
             (-1, 6.25)]
    for i, f in calls:
        rt.run(kernel, 1, buf, i, f, salts, local_size=1)
        cl.enqueue_copy(rt.queue, out, buf)
        assert out[0] == np.array(i).astype(np.int64).astype(np.uint32)
        assert out[1] == np.float32(f).view(np.uint32)
        np.testing.assert_array_equal(out[2:], np.array(salts.tolist(), np.uint32))


def test_a_pocl_without_devices_is_named_with_its_cache_folder(tmp_path):
    """PoCL lists no device when it cannot create its kernel cache folder (an
    XDG_CACHE_HOME that is a file); the selection error then said "install
    an OpenCL driver", naming neither PoCL nor the folder."""
    import subprocess
    blocked = tmp_path / "a_file"
    blocked.write_text("x")
    env = {k: v for k, v in os.environ.items()
           if k not in ("POCL_CACHE_DIR", "HLBVH_CL_DEVICE")}
    env.update(XDG_CACHE_HOME=str(blocked),
               PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    child = ("import warnings, pyopencl as cl\n"
             "warnings.simplefilter('ignore')\n"
             "empty = [p for p in cl.get_platforms() if 'Portable' in p.name\n"
             "         and not p.get_devices()]\n"
             "if not empty: print('SKIP'); raise SystemExit\n"
             "from hlbvh_cl.device import discovery\n"
             "discovery.devices()\n"
             "print(discovery.unregistered)\n")
    done = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True,
                          timeout=300)
    if done.stdout.strip() == "SKIP":
        pytest.skip("this PoCL lists its device without a cache folder")
    assert "lists no device" in done.stdout and "POCL_CACHE_DIR" in done.stdout, done.stdout
