"""Every program the library builds is standard OpenCL C 1.2.

CPU runtimes accept Clang's extensions to OpenCL C (variadic macros, say)
that a stricter compiler rejects: NVIDIA's refused all_hits.cl's variadic
macros ("variadic macros not supported in OpenCL").  Here every kernel file is
built on PoCL with Clang's pedantic diagnostics made errors, for each profile's
packet size, by running every query, builder and render once on a tiny scene.
The test also checks that this covered every kernel file, so a new one cannot
slip past it.
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl import device as device_module
from hlbvh_cl.order import COHERENT_MIN
from hlbvh_cl.paths import kernel_dir

#: Clang's pragmas (PoCL and NVIDIA's compilers are Clang) that turn every
#: extension to the language into an error, in the file and its headers; but
#: for a missing final newline, which PoCL's own _clang_opencl.h lacks.
PEDANTIC = ('#pragma clang diagnostic error "-Wpedantic"\n'
            '#pragma clang diagnostic ignored "-Wnewline-eof"\n')

#: Built by the probe's child, which compiles it with the device's own flags.
PROBE_ONLY = {"target_probe.cl"}


@pytest.fixture
def pedantic_kernels(tmp_path, monkeypatch, suite_device):
    """Runtimes made from here on build the pedantic copies of the kernels;
    returns the set of kernel files they built."""
    if not suite_device.id.startswith("pocl"):
        pytest.skip("the pragma is Clang's: checked on PoCL")
    folder = tmp_path / "kernels"
    shutil.copytree(kernel_dir(), folder)
    for source in folder.glob("*.cl"):
        source.write_text(PEDANTIC + source.read_text())
    monkeypatch.setattr(device_module, "kernel_dir", lambda: folder)
    monkeypatch.setattr(device_module, "_runtimes", {})  # fresh runtimes, nothing cached
    built = set()
    build = device_module.Runtime._build

    def recording(self, filename, defines):
        built.add(filename)
        return build(self, filename, defines)

    monkeypatch.setattr(device_module.Runtime, "_build", recording)
    return built


def _exercise(device) -> None:
    """Every query, both builders and both key widths, refit, instances
    (with masks and new transforms) and each shading, once each."""
    sphere = trimesh.creation.icosphere(subdivisions=1)
    mesh = hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere")
    rng = np.random.default_rng(1)
    # enough rays and points for the Morton-ordered launches (order.cl)
    origins = rng.uniform(-2, 2, (COHERENT_MIN, 3))
    directions = -origins + rng.normal(scale=0.1, size=origins.shape)
    for builder, bits in (("hlbvh", 30), ("lbvh", 63)):
        hlbvh_cl.Scene([mesh], device=device, builder=builder, morton_bits=bits)
    shift = np.eye(4)[:3]
    shift[:, 3] = (3, 0, 0)
    scenes = [hlbvh_cl.Scene([mesh], device=device),
              hlbvh_cl.Scene([mesh], device=device, instances=[(0, np.eye(4)), (0, shift)],
                             masks=[1, 2])]
    for scene in scenes:
        hits = scene.intersect(origins, directions)
        assert hits.hit.any()
        scene.occluded(origins, directions)
        assert scene.count_intersections(origins, directions).sum() > 0
        scene.intersect_all(origins, directions, max_hits=3)
        scene.closest_points(origins)
        scene.signed_distance(origins)
        scene.contains(origins)
        camera = hlbvh_cl.Camera(eye=(0, 0, 4), target=(0, 0, 0))
        for shading in ("diffuse", "normals", "depth", "ao"):
            hlbvh_cl.Renderer(scene).render(camera, 8, 6, shading=shading, ao_samples=2)
    scenes[0].update_vertices(0, sphere.vertices * 1.1)
    scenes[1].set_transforms([1], [np.eye(4)])
    scenes[1].intersect(origins, directions, mask=2)


@pytest.mark.parametrize("profile", ["cpu", "gpu"])
def test_every_kernel_builds_as_standard_opencl_c(pedantic_kernels, monkeypatch, suite_device,
                                                  profile):
    monkeypatch.setenv("HLBVH_CL_PROFILE", profile)
    _exercise(suite_device.id)
    every = {path.name for path in kernel_dir().glob("*.cl")} - PROBE_ONLY
    assert every - pedantic_kernels == set(), "kernel files this test never built"
