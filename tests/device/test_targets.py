"""The correctness tests on every other working device and profile.

The rest of the suite runs on one target (conftest: $HLBVH_CL_DEVICE, PoCL by
default, its own profile).  Each case here runs the correctness modules again
in a child pytest on one more target: every other device whose kernels run
(Intel's CPU runtime, a GPU where there is one), and the GPU profile forced on
the suite's device when that is a CPU, so that the path a GPU takes (one ray
per work-item, GPU work-group sizes, device copies) is tested where there is
no GPU.  The simulator has its own tier (test_oclgrind.py).
"""
import os
import sys
from pathlib import Path

import pytest

import hlbvh_cl

#: Modules (or single tests) that check results against an oracle or
#: invariants: ray semantics, the bad input and memory reuse of ray queries,
#: the point and all-hits queries and the input shapes, the pipeline stages,
#: rendering, and the struct layout.
CORRECTNESS = ["query/test_rays.py", "test_validation.py", "test_memory.py",
               "query/test_oracle.py", "query/test_points.py", "query/test_all_hits.py",
               "query/test_shapes.py", "build/test_instances.py", "test_travel.py",
               "query/test_embree.py", "query/test_watertight.py", "query/test_packets.py",
               "build/test_build.py", "build/test_radix_tree.py", "io/test_split.py",
               "parallel/test_sort.py", "parallel/test_scan.py", "build/test_widen.py",
               "render/test_render.py", "render/test_path.py", "render/test_shading_normals.py",
               "render/test_aovs.py",
               "build/test_extreme_coordinates.py",
               "device/test_devices.py::test_struct_layout_matches_device",
               "device/test_devices.py::test_constants_come_from_the_header"]

HERE = Path(__file__).resolve().parent.parent  # tests/

#: Seconds one child run may take (well over what the slowest takes).
CHILD_TIMEOUT_S = 1800

#: Memory one child run may take (the largest peak seen, about 4.3 GiB,
#: with room to spare): no more run at once than the free memory holds.
CHILD_MEMORY = 6 << 30


def _targets() -> list[tuple[str, str]]:
    """(device id, profile) pairs besides the suite's own."""
    if os.environ.get("HLBVH_CL_TARGET_CHILD"):
        return []  # already inside one of these runs
    main = hlbvh_cl.device.discovery.select_device()
    found = []
    for d in hlbvh_cl.devices():
        if d.simulator or d.problem is not None:
            continue
        if d.id != main.id:
            found.append((d.id, d.profile.name))
        if d.type == "cpu" and d.id == main.id:
            found.append((d.id, "gpu"))
    return found


def _child_job(device: str, profile: str) -> dict:
    from children import package_environment
    env = package_environment(HLBVH_CL_DEVICE=device, HLBVH_CL_PROFILE=profile,
                              HLBVH_CL_TARGET_CHILD="1")
    command = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
               *(str(HERE / name) for name in CORRECTNESS)]
    return {"args": command, "env": env, "cwd": HERE.parent, "timeout": CHILD_TIMEOUT_S}


@pytest.fixture(scope="module")
def target_children(request):
    """The selected targets' child runs, started side by side (children.py)."""
    from children import Children, selected_params, slots
    running = Children({(p["device"], p["profile"]): _child_job(p["device"], p["profile"])
                        for p in selected_params(request, test_correctness_suite_on)},
                       slots(CHILD_MEMORY))
    yield running
    running.close()


@pytest.mark.parametrize("device, profile", _targets())
def test_correctness_suite_on(device, profile, target_children):
    done = target_children.result((device, profile))
    summary = done.stdout.strip().splitlines()[-1:] or ["no output"]
    print(f"{device} ({profile} profile): {summary[0]}")
    assert done.returncode == 0, f"{device} with the {profile} profile:\n{done.stdout[-6000:]}" \
                                 f"\n{done.stderr[-2000:]}"
