"""Every program the library builds is standard OpenCL C 1.2.

CPU runtimes accept Clang's extensions to OpenCL C (variadic macros, say)
that a stricter compiler rejects: NVIDIA's refused all_hits.cl's variadic
macros ("variadic macros not supported in OpenCL").  Here every kernel file is
built on PoCL with Clang's pedantic diagnostics made errors, for each profile's
packet size, by running every query, builder and render once on a tiny scene.
The test also checks that this covered every kernel file, so a new one cannot
slip past it.

Each case runs in a child process (this file as a script), the cases side by
side (children.py): their time is the compiler's, on one core each.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl.device import runtime as device_module
from hlbvh_cl.query.order import COHERENT_MIN
from hlbvh_cl.core.paths import kernel_dir

#: Clang's pragmas (PoCL and NVIDIA's compilers are Clang) that turn every
#: extension to the language into an error, in the file and its headers; but
#: for a missing final newline, which PoCL's own _clang_opencl.h lacks.
PEDANTIC = ('#pragma clang diagnostic error "-Wpedantic"\n'
            '#pragma clang diagnostic ignored "-Wnewline-eof"\n')

#: Built by the probe's child, which compiles it with the device's own flags.
PROBE_ONLY = {"device/probe.cl"}


#: What OpenCL C lacks on a device without cl_khr_fp64: the extension's
#: macros, and the double constants the spec gives only with it (6.13.2.1;
#: Clang's opencl-c-base.h defines them only then).
NO_FP64 = "".join(f"#undef {name}\n" for name in (
    "cl_khr_fp64", "__opencl_c_fp64", "HUGE_VAL", "DBL_DIG", "DBL_MANT_DIG", "DBL_MAX_10_EXP",
    "DBL_MAX_EXP", "DBL_MIN_10_EXP", "DBL_MIN_EXP", "DBL_RADIX", "DBL_MAX", "DBL_MIN",
    "DBL_EPSILON", "M_E", "M_LOG2E", "M_LOG10E", "M_LN2", "M_LN10", "M_PI", "M_PI_2", "M_PI_4",
    "M_1_PI", "M_2_PI", "M_2_SQRTPI", "M_SQRT2", "M_SQRT1_2"))


def _kernel_copies(folder: Path, prelude: str) -> set:
    """Runtimes made from here on, in this (child) process, build copies of
    the kernels, in `folder`, with `prelude` before each file; returns the
    set of kernel files they built."""
    shutil.copytree(kernel_dir(), folder)
    for source in folder.rglob("*.cl"):
        source.write_text(prelude + source.read_text())
    device_module.kernel_dir = lambda: folder
    device_module.forget_runtimes()  # fresh runtimes, nothing cached
    built = set()
    program = device_module.Runtime.program

    def recording(self, filename, **defines):
        # a fresh runtime builds each program the first time it is asked for
        built.add(filename)
        return program(self, filename, **defines)

    device_module.Runtime.program = recording
    return built


def _exercise(device) -> None:
    """Every query, both builders and both key widths, refit, instances
    (with masks and new transforms, and compact) and each shading, once each."""
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
        # rays and points on the device (on_device.cl; camera.cl's camera_rays)
        on_device = camera.rays(8, 6, scene=scene)
        scene.intersect(*on_device)
        scene.closest_points(on_device[1])
        for shading in ("diffuse", "normals", "depth", "ao"):
            hlbvh_cl.Renderer(scene).render(camera, 8, 6, shading=shading, ao_samples=2)
        # the path stages with every BSDF and light kind, and the film's float image
        materials = [{"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}]
        for material in ({"type": "diffuse"}, {"type": "conductor"}, {"type": "dielectric"},
                         *materials):
            hlbvh_cl.Renderer(scene, materials=[material], emitters=[
                {"type": "area", "mesh": 0, "radiance": 1.0},
                {"type": "point", "position": [0, 3, 0], "intensity": 1.0},
                {"type": "directional", "direction": [0, -1, 0], "irradiance": 1.0},
                {"type": "constant", "radiance": 0.5}]).render(
                camera, 8, 6, shading="path", spp=2, max_depth=3, rfilter="gaussian", hdr=True)
        sky = np.linspace(0.1, 2.0, 4 * 8 * 3, dtype=np.float32).reshape(4, 8, 3)
        hlbvh_cl.Renderer(scene, emitters=[{"type": "envmap", "image": sky}]).render(
            camera, 8, 6, shading="path", spp=2, max_depth=3, hdr=True)
    from hlbvh_cl.render.sampling import eval_bsdf, eval_envmap, sample_bsdf, sample_envmap
    for material in ({"type": "diffuse"}, *materials):
        drawn = sample_bsdf(material, (0, 0, 1), 16, device=device)
        eval_bsdf(material, (0, 0, 1), drawn["directions"], device=device)
    drawn = sample_envmap({"type": "envmap", "image": sky}, 16, device=device)
    eval_envmap({"type": "envmap", "image": sky}, drawn["directions"], device=device)
    scenes[0].update_vertices(0, sphere.vertices * 1.1)
    scenes[1].set_transforms([1], [np.eye(4)])
    scenes[1].intersect(origins, directions, mask=2)
    # compact meshes' trees joined (instances.cl), read through their records
    compact = hlbvh_cl.Scene([mesh, mesh], device=device, instances=[(0, np.eye(4)), (1, shift)],
                             compact=True)
    assert compact.intersect(origins, directions).hit.any()


def _answers(device) -> dict:
    """Closest hits, counts, closest points and signed distances on a
    closed mesh and on two instances of it."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    mesh = hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere")
    rng = np.random.default_rng(2)
    origins = rng.uniform(-2, 2, (3 * COHERENT_MIN, 3))
    directions = rng.uniform(-1, 1, (1, 3)) * 0.2 - origins
    shift = np.eye(4)[:3]
    shift[:, 3] = (1.5, 0, 0)
    found = {}
    for name, scene in (("flat", hlbvh_cl.Scene([mesh], device=device)),
                        ("instanced", hlbvh_cl.Scene([mesh], device=device,
                                                     instances=[(0, np.eye(4)), (0, shift)]))):
        hits = scene.intersect(origins, directions)
        closest = scene.closest_points(origins)
        found[name] = {"prim_id": hits.prim_id, "t": hits.t,
                       "counts": scene.count_intersections(origins, directions),
                       "distance": closest.distance,
                       "signed": scene.signed_distance(origins)}
    return found


#: The cases, each a child: (kernel prelude, profile, whether it answers too).
CASES = {"pedantic-cpu": (PEDANTIC, "cpu", False), "pedantic-gpu": (PEDANTIC, "gpu", False),
         "no-fp64": (NO_FP64, None, True)}

#: Seconds one child may take (far more than any needs).
CHILD_TIMEOUT_S = 900

#: Memory one child may take (see children.slots): a tiny scene's queries.
CHILD_MEMORY = 2 << 30


def child(case: str, folder: str) -> None:
    """One case, in this process: every kernel built from its copies (and
    the answers, for no-fp64); the built files and the answers go to
    `folder` (built.json, answers.npz)."""
    prelude, _, answers = CASES[case]
    device = os.environ["HLBVH_CL_DEVICE"]
    built = _kernel_copies(Path(folder) / "kernels", prelude)
    if answers:
        found = _answers(device)
        np.savez(Path(folder) / "answers.npz",
                 **{f"{name}/{key}": value for name, values in found.items()
                    for key, value in values.items()})
    _exercise(device)
    (Path(folder) / "built.json").write_text(json.dumps(sorted(built)))


if __name__ == "__main__":
    child(*sys.argv[1:])
    sys.exit(0)


def _pocl_only(device) -> None:
    if not device.id.startswith("pocl"):
        pytest.skip("the pragma and the copies' preludes are Clang's: checked on PoCL")


def _case(item) -> str | None:
    """The case a selected test needs, if it is one of this file's."""
    function = getattr(item, "function", None)
    if function is test_every_kernel_builds_as_standard_opencl_c:
        return f"pedantic-{item.callspec.params['profile']}"
    if function is test_kernels_without_fp64_build_and_answer_as_with_it:
        return "no-fp64"
    return None


@pytest.fixture(scope="module")
def case_children(request, tmp_path_factory, suite_device):
    """The selected tests' cases, started side by side in children
    (children.py): (Children, {case: its folder})."""
    from children import Children, package_environment, slots
    _pocl_only(suite_device)
    selected = {_case(item) for item in request.session.items} - {None}
    folders = {case: tmp_path_factory.mktemp(case) for case in CASES if case in selected}
    env = package_environment(HLBVH_CL_DEVICE=suite_device.id)
    jobs = {}
    for case, folder in folders.items():
        profile = CASES[case][1]
        jobs[case] = {"args": [sys.executable, __file__, case, str(folder)],
                      "env": {**env, "HLBVH_CL_PROFILE": profile} if profile else env,
                      "timeout": CHILD_TIMEOUT_S}
    running = Children(jobs, slots(CHILD_MEMORY))
    yield running, folders
    running.close()


def _finished(case_children, case: str) -> Path:
    """The case's folder, once its child has built every kernel file."""
    running, folders = case_children
    done = running.result(case)
    assert done.returncode == 0, f"the {case} case exited with {done.returncode}:\n" \
                                 f"{done.stderr[-6000:]}"
    built = set(json.loads((folders[case] / "built.json").read_text()))
    every = {path.relative_to(kernel_dir()).as_posix()
             for path in kernel_dir().rglob("*.cl")} - PROBE_ONLY
    assert every - built == set(), "kernel files this test never built"
    return folders[case]


@pytest.mark.parametrize("profile", ["cpu", "gpu"])
def test_every_kernel_builds_as_standard_opencl_c(case_children, profile):
    _finished(case_children, f"pedantic-{profile}")


def test_kernels_without_fp64_build_and_answer_as_with_it(case_children, suite_device):
    """Every kernel builds where the device has no doubles (no cl_khr_fp64,
    no double constants such as M_PI), and the float fallbacks give the
    answers the double paths give: the same triangles, counts and signs, t
    and distances within float rounding."""
    expected = _answers(suite_device.id)
    with np.load(_finished(case_children, "no-fp64") / "answers.npz") as saved:
        got = {name: {key: saved[f"{name}/{key}"] for key in answers}
               for name, answers in expected.items()}
    for name, answers in expected.items():
        assert (answers["prim_id"] >= 0).sum() > 50
        np.testing.assert_array_equal(got[name]["prim_id"], answers["prim_id"])
        np.testing.assert_allclose(got[name]["t"], answers["t"], rtol=1e-5)
        np.testing.assert_array_equal(got[name]["counts"], answers["counts"])
        np.testing.assert_allclose(got[name]["distance"], answers["distance"], rtol=1e-5,
                                   atol=1e-6)
        np.testing.assert_array_equal(np.sign(got[name]["signed"]), np.sign(answers["signed"]))
        np.testing.assert_allclose(got[name]["signed"], answers["signed"], rtol=1e-5, atol=1e-6)
