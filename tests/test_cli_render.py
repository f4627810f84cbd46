"""Smoke tests of `hlbvh-cl render`: images of the right size, timings
printed, and a user's mistakes reported in one line with exit code 2."""
import signal
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from hlbvh_cl.cli import main
from hlbvh_cl.io import scenefile
import places

SCENES = places.SCENES
BUNNY = str(SCENES / "bunny_small.toml")


def test_render_writes_the_image_and_prints_the_times(tmp_path, capsys):
    out = tmp_path / "bunny.png"
    assert main(["render", BUNNY, "-o", str(out), "--width", "64", "--height", "48"]) == 0
    image = iio.imread(out)
    assert image.shape == (48, 64, 3) and image.dtype == np.uint8
    # the scene file's colours: its mesh colour appears, not only sky and ground
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 20
    printed = capsys.readouterr().out
    for word in ("load", "build", "trace+shade", "compile", "write", "64x48", "diffuse"):
        assert word in printed


def test_render_takes_the_scene_file_size_and_the_options(tmp_path, capsys, suite_device):
    description = scenefile.read(BUNNY)
    out = tmp_path / "normals.png"
    assert main(["render", BUNNY, "-o", str(out), "--shading", "normals", "--spp", "2",
                 "--height", "30"]) == 0
    assert iio.imread(out).shape == (30, description.width, 3)
    assert "normals" in capsys.readouterr().out
    out = tmp_path / "ao.png"
    assert main(["render", BUNNY, "-o", str(out), "--shading", "ao", "--ao-samples", "2",
                 "--width", "20", "--height", "10", "--device", suite_device.id]) == 0
    assert iio.imread(out).shape == (10, 20, 3)


def _one_line_error(capsys) -> str:
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.startswith("hlbvh-cl: error:") and "\n" not in err, err
    return err


@pytest.mark.parametrize("arguments, words", [
    (["render", "missing.toml", "-o", "x.png"], "missing.toml"),
    (["render", BUNNY, "-o", "x.png", "--spp", "0"], "--spp"),
    (["render", BUNNY, "-o", "x.png", "--width", "wide"], "--width"),
    (["render", BUNNY, "-o", "x.png", "--width", "20000"], "width"),
    (["render", BUNNY, "-o", "x.png", "--shading", "phong"], "--shading"),
    (["render", BUNNY, "-o", "x.png", "--device", "nope"], "nope"),
    (["render", BUNNY, "-o", "x.unknown"], "x.unknown"),
    (["render", BUNNY, "-o", "no/such/folder/x.png"], "does not exist"),
    (["render", BUNNY], "-o"),
])
def test_user_mistakes_give_one_line_and_exit_2(arguments, words, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(arguments) == 2
    assert words in _one_line_error(capsys)
    assert not (tmp_path / "x.png").exists()


def test_a_bad_scene_file_gives_one_line(tmp_path, capsys):
    broken = tmp_path / "broken.toml"
    broken.write_text('[render]\nwidth = 0\nheight = 10\n[camera]\neye = [0, 0, 1]\n'
                      'target = [0, 0, 0]\n[[mesh]]\npath = "m.ply"\n')
    assert main(["render", str(broken), "-o", str(tmp_path / "x.png")]) == 2
    assert "render.width" in _one_line_error(capsys)


def test_the_console_script_reports_without_traceback(tmp_path):
    done = subprocess.run([sys.executable, "-m", "hlbvh_cl", "render", str(tmp_path / "none.toml"),
                           "-o", str(tmp_path / "x.png")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().startswith("hlbvh-cl: error:") and "Traceback" not in done.stderr


def test_the_output_may_not_be_a_file_the_scene_reads(tmp_path, monkeypatch, capsys):
    """`-o` naming a file the scene reads (its own file under an image's
    name, its environment map) is refused, the file untouched, before the
    scene is built: the render had overwritten them and exited 0.  (A mesh
    file's suffix is never an image's.)"""
    import shutil
    from hlbvh_cl.io.exr import write_exr
    write_exr(tmp_path / "sky.exr", np.full((4, 8, 3), 0.5, np.float32))
    shutil.copy(SCENES / "meshes" / "bunny_small.ply", tmp_path / "bunny.ply")
    scene = tmp_path / "scene.png"  # a TOML scene under an image's name
    scene.write_text('[render]\nwidth = 16\nheight = 12\n[camera]\neye = [0, 0.1, 0.4]\n'
                     'target = [0, 0.1, 0]\n[[mesh]]\npath = "bunny.ply"\n'
                     '[[emitter]]\ntype = "envmap"\nfilename = "sky.exr"\n')
    sources = {path: path.read_bytes() for path in tmp_path.iterdir()}

    def no_build(*args, **kwargs):
        raise AssertionError("the scene was built before the output was checked")
    monkeypatch.setattr(scenefile, "Scene", no_build)
    for name in ("scene.png", "sky.exr"):
        assert main(["render", str(scene), "-o", str(tmp_path / name)]) == 2
        # the last line (a slow first build may say what it is doing before it)
        assert "the scene reads it" in capsys.readouterr().err.strip().splitlines()[-1]
    assert {path: path.read_bytes() for path in tmp_path.iterdir()} == sources


def test_a_device_file_is_not_read_as_a_scene(capsys):
    """/dev/zero named as the scene was read whole (a MemoryError traceback
    under a memory limit, else without end)."""
    assert main(["render", "/dev/zero", "-o", "x.png"]) == 2
    assert "/dev/zero: not a regular file" in _one_line_error(capsys)


def test_a_ctrl_c_swallowed_while_the_scene_loads_still_stops(tmp_path, monkeypatch, capsys):
    """Code that catches BaseException while the scene loads (trimesh's
    optional imports) swallowed Ctrl-C, and the render ran to the end: the
    command remembers it and stops after loading, writing nothing."""
    load = scenefile.load

    def swallowing(*args, **kwargs):
        try:  # a real SIGINT, through the handler the command installed
            signal.raise_signal(signal.SIGINT)
        except BaseException:  # as trimesh's optional imports do
            pass
        return load(*args, **kwargs)
    monkeypatch.setattr(scenefile, "load", swallowing)
    out = tmp_path / "x.png"
    assert main(["render", BUNNY, "-o", str(out), "--width", "8", "--height", "8"]) == 130
    assert "interrupted" in capsys.readouterr().err and not out.exists()


def test_warnings_are_one_line_each(tmp_path, monkeypatch, capsys):
    """A warning during a command (e.g. a runtime not listed) showed
    Python's form: our source file and line, then the line of code."""
    import warnings
    load = scenefile.load

    def warning(*args, **kwargs):
        warnings.warn("something to know", RuntimeWarning)
        return load(*args, **kwargs)
    monkeypatch.setattr(scenefile, "load", warning)
    assert main(["render", BUNNY, "-o", str(tmp_path / "x.png"), "--width", "8",
                 "--height", "8"]) == 0
    lines = capsys.readouterr().err.strip().splitlines()  # (and any slow step's progress line)
    assert "hlbvh-cl: warning: something to know" in lines
    assert not any("warnings.warn" in line or ".py:" in line for line in lines), lines
