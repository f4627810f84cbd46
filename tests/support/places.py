"""Where the suite finds the checkout's files, from any folder of tests/."""
from pathlib import Path

#: the checkout: hlbvh_cl/, kernels/, scenes/, tests/, bench/
REPO = Path(__file__).resolve().parents[2]
TESTS = REPO / "tests"
SUPPORT = TESTS / "support"
SCENES = REPO / "scenes"
MESHES = SCENES / "meshes"
