"""Smoke tests of the hlbvh-cl command."""
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from hlbvh_cl.cli import main

SCENES = Path(__file__).resolve().parent.parent / "scenes"


def test_devices_lists_and_requires_the_suite_device(capsys, suite_device):
    assert main(["devices", "--require", suite_device.id]) == 0
    assert suite_device.id in capsys.readouterr().out


def test_info_prints_stats(capsys):
    assert main(["info", str(SCENES / "bunny_small.toml"), "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "triangles" in out and "SAH cost" in out and "bounds" in out


def test_user_mistakes_give_one_line_and_exit_2(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing.toml")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hlbvh-cl: error:") and "missing.toml" in err and "\n" not in err
    assert main(["info", str(SCENES / "bunny_small.toml"), "--device", "nope"]) == 2
    assert main(["info", str(SCENES / "bunny_small.toml"), "--repeat", "0"]) == 2
    capsys.readouterr()
    (tmp_path / "folder.toml").mkdir()
    assert main(["render", str(tmp_path / "folder.toml"), "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hlbvh-cl: error:") and "folder.toml" in err and "\n" not in err


@pytest.mark.parametrize("argv, words", [
    (["devices", "--no-fallback"], "--no-fallback applies to --require ID, which is missing"),
    (["render", "s.toml", "-o", "x.png", "--ao-samples", "4"],
     "--ao-samples applies to --shading ao, not diffuse"),
    (["render", "s.toml", "-o", "x.png", "--shading", "depth", "--no-shadows"],
     "--no-shadows applies to --shading diffuse, not depth"),
])
def test_an_option_the_others_make_meaningless_is_refused(capsys, argv, words):
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == f"hlbvh-cl: error: {words}"


def test_main_leaves_the_callers_warning_filters_alone():
    before = list(warnings.filters)
    assert main(["info", str(SCENES / "bunny_small.toml"), "--repeat", "1"]) == 0
    assert warnings.filters == before


def test_console_script_runs(suite_device):
    done = subprocess.run([sys.executable, "-m", "hlbvh_cl", "devices"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0 and suite_device.id in done.stdout
