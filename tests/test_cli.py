"""Smoke tests of the hlbvh-cl command."""
import subprocess
import sys
import warnings

import pytest

from hlbvh_cl.cli import main
from hlbvh_cl.io.scenefile import load
from hlbvh_cl.render.settings import MAX_SPP
import places

SCENES = places.SCENES


def test_devices_lists_and_requires_the_suite_device(capsys, suite_device):
    assert main(["devices", "--require", suite_device.id]) == 0
    assert suite_device.id in capsys.readouterr().out


def test_info_prints_stats(capsys):
    assert main(["info", str(SCENES / "bunny_small.toml"), "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "triangles" in out and "SAH cost" in out and "bounds" in out
    stats = load(SCENES / "bunny_small.toml").scene.stats  # the same tree, built again
    assert (f"nodes {stats.node_bytes:,} B + leaf triangles {stats.triangle_bytes:,} B"
            in out) and stats.node_bytes > 0 and stats.triangle_bytes > 0


def test_info_compact_prints_the_compact_trees_memory(capsys):
    assert main(["info", str(SCENES / "bunny_small.toml"), "--repeat", "1", "--compact"]) == 0
    out = capsys.readouterr().out
    stats = load(SCENES / "bunny_small.toml", compact=True).scene.stats
    assert stats.triangle_bytes < load(SCENES / "bunny_small.toml").scene.stats.triangle_bytes
    assert f"nodes {stats.node_bytes:,} B + compact leaves {stats.triangle_bytes:,} B" in out


def test_info_on_instances_prints_the_meshes_trees_memory(tmp_path, capsys):
    """An instanced scene's stats are its top tree's; its meshes' trees, which
    hold the triangles, get their own line, compact where asked."""
    mesh = (SCENES / "meshes" / "bunny_small.ply").resolve()
    path = tmp_path / "copies.toml"
    # bunny_small.toml's render and camera, its mesh placed three times
    head = (SCENES / "bunny_small.toml").read_text().split("[ground]")[0]
    path.write_text(head + f'[[mesh]]\npath = "{mesh.as_posix()}"\n\n[[instance]]\nmesh = 0\n'
                    'translate = [[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 0.0, 30.0]]\n')
    printed = {}
    for compact in (False, True):
        assert main(["info", str(path), "--repeat", "1"] + ["--compact"] * compact) == 0
        out = capsys.readouterr().out
        assert "3 instances" in out
        with load(path, compact=compact).scene.borrow() as built:
            held = built.tree.meshes.memory()
        leaves = "compact leaves" if compact else "leaf triangles"
        assert (f"nodes {held['node_bytes']:,} B + {leaves} {held['triangle_bytes']:,} B"
                in out), out
        printed[compact] = held["triangle_bytes"]
    assert 0 < printed[True] < printed[False]


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
    (["render", "s.toml", "-o", "x.png", "--max-depth", "3"],
     "--max-depth applies to --shading path, not diffuse"),
    (["render", "s.toml", "-o", "x.png", "--time", "10"],
     "--time applies to --shading path, not diffuse"),
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


def test_version_needs_no_command(capsys):
    import hlbvh_cl
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"hlbvh-cl {hlbvh_cl.__version__}"


def test_a_mesh_file_renders_as_a_scene_of_that_mesh(tmp_path, capsys, suite_device):
    """`hlbvh-cl render bunny.ply` frames the mesh on a ground (scenefile.read_mesh)."""
    import imageio.v3 as iio
    import numpy as np
    import trimesh
    mesh = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=2).export(mesh)
    out = tmp_path / "ball.png"
    assert main(["render", str(mesh), "-o", str(out), "--width", "64", "--height", "48",
                 "--device", suite_device.id]) == 0
    assert "ball.ply: 2 meshes" in capsys.readouterr().out  # the ball and its ground
    image = iio.imread(out)
    assert image.shape == (48, 64, 3)
    # framed: the ball (lit grey, off the sky's blue-white) covers the centre
    centre = image[18:30, 26:38].astype(int)
    assert (np.abs(centre[..., 2] - centre[..., 0]) < 8).all()
    assert main(["info", str(mesh), "--repeat", "1", "--device", suite_device.id]) == 0
    assert "triangles  322" in capsys.readouterr().out  # 320 + the ground's 2


def test_a_path_traced_render_names_its_rays(tmp_path, capsys, suite_device):
    """--shading path with --max-depth: the image, and the bounce and
    shadow rays it traced in the report; a depth of 0 is refused."""
    import imageio.v3 as iio
    import numpy as np
    import trimesh
    mesh = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=2).export(mesh)
    out = tmp_path / "ball.png"
    assert main(["render", str(mesh), "-o", str(out), "--width", "32", "--height", "24",
                 "--shading", "path", "--spp", "2", "--max-depth", "3",
                 "--device", suite_device.id]) == 0
    report = capsys.readouterr().out
    assert "path, 2 spp, 1,536 primary + " in report and " bounce and shadow rays" in report
    assert iio.imread(out).shape == (24, 32, 3)
    assert main(["render", str(mesh), "-o", str(out), "--shading", "path",
                 "--max-depth", "0"]) == 2
    # an .exr gets the float32 linear means: what Renderer.render(hdr=True) gives
    from hlbvh_cl.io.exr import read_exr
    from hlbvh_cl.io.scenefile import load
    exr = tmp_path / "ball.exr"
    assert main(["render", str(mesh), "-o", str(exr), "--width", "32", "--height", "24",
                 "--shading", "path", "--spp", "2", "--max-depth", "3",
                 "--device", suite_device.id]) == 0
    loaded = load(mesh, suite_device.id)
    expected = loaded.renderer().render(loaded.camera, 32, 24, shading="path", spp=2,
                                        max_depth=3, hdr=True)
    assert np.array_equal(read_exr(exr), expected) and expected.max() > 0.1
    assert "expected -1 (no limit) or 1..1024, got 0" in capsys.readouterr().err


def test_a_file_neither_toml_nor_mesh_says_what_is_expected(tmp_path, capsys):
    """Binary or text, a file of another suffix that is not TOML is named
    by its suffix and the formats taken (a .gltf mesh had been reported as
    a TOML syntax error); without a suffix, as not TOML."""
    binary = tmp_path / "scan.bin"
    binary.write_bytes(bytes([0xF3, 0x00, 0xFF, 0x80]) * 64)
    gltf = tmp_path / "box.gltf"
    gltf.write_text('{"asset": {"version": "2.0"}, "meshes": []}')
    for path in (binary, gltf):
        assert main(["render", str(path), "-o", str(tmp_path / "x.png")]) == 2
        err = capsys.readouterr().err.strip()
        assert f"a {path.suffix} file is neither a scene file (.toml, .xml) nor a mesh file " \
               "this reader takes (.ply, .obj" in err and "\n" not in err, err
    bare = tmp_path / "scan"
    bare.write_bytes(binary.read_bytes())
    assert main(["render", str(bare), "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert "not UTF-8 text, so not a TOML scene file (expected a .toml scene file, or a mesh " \
           "file: .ply, .obj" in err and "\n" not in err


def test_a_slow_step_says_what_it_does_and_a_quick_one_is_quiet(capsys):
    import time
    from hlbvh_cl.cli import stage
    with stage("compiling", after_s=0.05):
        time.sleep(0.3)
    with stage("quick", after_s=5.0):
        pass
    assert capsys.readouterr().err == "hlbvh-cl: compiling ...\n"


def test_ctrl_c_ends_a_render_with_one_line_and_exit_130(tmp_path, suite_device):
    """SIGINT during a long render: no traceback, the shell's code for it.
    The render is long on any device: 64 spp of 4096 x 4096 ended before the
    signal below on an H200, so it takes MAX_SPP."""
    import os
    import signal
    import time
    done_marker = tmp_path / "never.png"
    command = [sys.executable, "-m", "hlbvh_cl", "render", str(SCENES / "bunny_small.toml"),
               "-o", str(done_marker), "--width", "4096", "--height", "4096", "--spp", str(MAX_SPP),
               "--device", suite_device.id]
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONUNBUFFERED": "1"})
    time.sleep(8)  # past start-up, into the build or the render
    child.send_signal(signal.SIGINT)
    out, err = child.communicate(timeout=120)
    assert child.returncode == 130, err[-2000:]
    assert err.strip().splitlines()[-1] == "hlbvh-cl: interrupted" and "Traceback" not in err
    assert not done_marker.exists()
