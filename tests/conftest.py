"""The suite runs on PoCL's CPU device unless HLBVH_CL_DEVICE says otherwise.
Tree invariants are checked where trees are made: tests/support/invariants.py's
check_tree, which the build tests call."""
import os
import sys
from pathlib import Path

import pytest

# tests/support: the oracles, shapes and helpers every room's tests import
sys.path.insert(0, str(Path(__file__).resolve().parent / "support"))

os.environ.setdefault("HLBVH_CL_DEVICE", "pocl")

MESH_DIR = Path(__file__).resolve().parent.parent / "scenes" / "meshes"


def pytest_report_header(config):
    """What this run ran on: every device with its probe's verdict."""
    import hlbvh_cl
    from hlbvh_cl.cli import device_state
    lines = [f"hlbvh_cl target: {os.environ['HLBVH_CL_DEVICE']}, profile "
             f"{os.environ.get('HLBVH_CL_PROFILE') or 'by device type'}"]
    lines += [f"  {d.id} ({d.type}) {d.name}: {device_state(d)}" for d in hlbvh_cl.devices()]
    return lines


@pytest.fixture(scope="session")
def suite_device():
    """The device this run tests: the one $HLBVH_CL_DEVICE names (tests name
    it through this, never a vendor of their own)."""
    from hlbvh_cl.device.discovery import select_device
    return select_device(os.environ["HLBVH_CL_DEVICE"])


@pytest.fixture(scope="module")
def meshes():
    """The project's meshes by name (scenes/meshes/NAME.ply), each loaded the
    first time a test asks for it."""
    from hlbvh_cl import Mesh

    class Loaded(dict):
        def __missing__(self, name):
            self[name] = mesh = Mesh.load(MESH_DIR / f"{name}.ply")
            return mesh

    return Loaded()
