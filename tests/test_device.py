"""Device listing, selection, program caching and build errors."""
import os
import sys
from pathlib import Path

import pytest

import hlbvh_cl
from hlbvh_cl import device as device_module
from hlbvh_cl.device import KernelBuildError, Runtime, runtime, select_device


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
    monkeypatch.setattr(device_module, "_devices_cache", [])
    with pytest.raises(RuntimeError, match="pip install pocl-binary-distribution"):
        select_device()


@pytest.mark.skipif(not (Path(sys.prefix) / "lib" / "libintelocl.so").is_file(),
                    reason="intel-opencl-rt is not installed")
def test_intel_cpu_runtime_is_found_without_user_icd_files():
    if "OCL_ICD_VENDORS" in os.environ and "hlbvh_cl" not in os.environ["OCL_ICD_VENDORS"]:
        pytest.skip("the user's own OCL_ICD_VENDORS is in force")
    assert any(d.id.startswith("intel:") for d in hlbvh_cl.devices())


def test_programs_are_built_once_and_cached():
    rt = runtime()
    assert rt.program("bounds.cl", STRIDED_SLICES=0) is rt.program("bounds.cl", STRIDED_SLICES=0)
    assert rt.kernel("morton.cl", "morton_codes", MORTON_BITS=30) is \
        rt.kernel("morton.cl", "morton_codes", MORTON_BITS=30)


def test_compile_error_shows_the_build_log(tmp_path, monkeypatch):
    (tmp_path / "hlbvh.h").write_text("")
    (tmp_path / "broken.cl").write_text("__kernel void f(__global int *x) { x[0] = nope; }\n")
    monkeypatch.setattr(device_module, "kernel_dir", lambda: tmp_path)
    rt = Runtime(select_device())
    with pytest.raises(KernelBuildError, match="broken.cl failed to build") as info:
        rt.program("broken.cl")
    assert "nope" in str(info.value)  # the compiler's own message is in the log


@pytest.mark.skipif(not (Path(sys.prefix) / "lib" / "libintelocl.so").is_file(),
                    reason="intel-opencl-rt is not installed")
def test_a_runtime_that_cannot_be_registered_says_why(tmp_path):
    """A user's OCL_ICD_VENDORS folder without Intel's .icd hides the runtime:
    devices() warns and the error for device='intel' names the reason."""
    import subprocess
    child = ("import warnings, hlbvh_cl\n"
             "from hlbvh_cl.device import select_device\n"
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
    assert "matches no OpenCL device" in error and "not registered: Intel's CPU runtime" in error


def test_importing_changes_nothing_outside_the_package():
    import subprocess
    child = ("import os; before = dict(os.environ); import pyopencl; before = dict(os.environ)\n"
             "import hlbvh_cl; print(dict(os.environ) == before)")
    env = {k: v for k, v in os.environ.items() if k != "OCL_ICD_VENDORS"}
    done = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.stdout.strip() == "True", done.stderr
