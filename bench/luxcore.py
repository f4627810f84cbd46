"""LuxCore's PATHCPU as a bench participant: a scene bench.path renders (the
SceneDescription that hlbvh_cl.io.scenefile.read gives of the same XML file)
translated to LuxCore scene properties, and timed renders of it.

pyluxcore is optional: ``available()`` says whether it imports (numpy must be
imported first, or the process aborts: RENDERING.md; so must the OpenEXR
module, before an envmap's file is read: _pyluxcore).  It runs in a child
process (LuxCoreChild): imported beside Mitsuba it aborts the process.

The translation, and what in it is approximate:
  meshes     Scene.DefineMeshExt with the placed vertices, faces and (unless the
             mesh is flat-shaded) our vertex normals, as numpy arrays; no files.
  camera     lookat + fieldofview with an explicit screenwindow of
             [-aspect, aspect] x [-1 - 2 / height, 1 - 2 / height]: LuxCore's
             fieldofview spans the unit range of the screen window, and its
             automatic window puts that on the image's longer side, whereas
             ours (and Mitsuba's after our reader's fov_axis conversion) is
             the vertical field of view.  The window is one pixel (2 / height)
             lower because LuxCore's picture otherwise sits one row lower than
             ours: found by rendering a box's shadow on a floor at 48 x 32,
             40 x 40 and 30 x 60, where ours moved down by 1.0 row matched
             LuxCore's best (of shifts in quarter rows), and with the lowered
             window no shift does better, in rows or columns.
  diffuse    matte (kd).  LuxCore's materials are two-sided, Mitsuba's diffuse
             is black from behind: the same wherever the camera sees fronts.
  dielectric glass (interiorior / exteriorior, kr / kt).
  roughdielectric  roughglass, same roughness mapping as metal2.
  conductor / roughconductor  metal2 with n = eta and k (Mitsuba's
             defaults 0 and 1 when absent, a perfect mirror), or a named
             metal's ("material": "Au") from the table our own loader uses
             (hlbvh_cl.render.metals: Mitsuba's RGB values).  metal2's
             microfacet distribution is Schlick's form with r = uroughness *
             vroughness, D = r / (pi (1 + (r - 1) cos^2)^2), which is GGX with
             alpha^2 = r: so uroughness = vroughness = Mitsuba's GGX alpha.  Its shadowing
             term is Schlick's approximation, not GGX's Smith G.  A Beckmann
             alpha is passed the same way (approximate).  A smooth conductor
             gets roughness SMOOTH (LuxCore has no delta conductor with n, k).
             specular_reflectance is not mapped.
  plastic / roughplastic  glossy2 (approximate: LuxCore's glossy2 is the
             Ashikhmin-Shirley coating over a diffuse base, Mitsuba's
             roughplastic a GGX coating with internal scattering): kd = the
             diffuse reflectance, ks = Fresnel reflectance at normal
             incidence ((eta - 1) / (eta + 1))^2 of int_ior / ext_ior, the
             same roughness mapping; smooth plastic gets roughness SMOOTH;
             nonlinear is not mapped.
  twosided   the inner BSDF (LuxCore's are two-sided already).
  area       emission on the mesh's material, gain 1 (radiance = the colour;
             no power / efficacy normalisation), front side only as Mitsuba.
  constant   constantinfinite (color, gain 1).
  point      point (color = intensity, gain 1, no power normalisation).
  directional  sharpdistant (direction, color = the irradiance, gain 1): both
             take the direction the light travels, and LuxCore's colour is
             the irradiance on a surface facing it (seen by rendering: a
             diffuse floor's radiance is reflectance / pi * E cos, and the
             floor is black with the direction negated).
  envmap     infinite with the same file, gamma 1 (the file is linear
             radiance), gain = scale, and a transformation that turns
             LuxCore's latitude-longitude frame into Mitsuba's (ENVMAP_FRAME)
             before the emitter's to_world rotation.  Found by rendering a
             map whose texels hold their own (u, v): LuxCore's top row looks
             along +z and u = atan2(y, x) / (2 pi), Mitsuba's top row along
             +y and u = atan2(x, -z) / (2 pi) (hlbvh_cl/render/envmap.py).
             The two turn in opposite senses around the pole, so the frame
             change is a mirror (determinant -1), which LuxCore applies as
             given.  Approximate: LuxCore's image lookup puts rows at texel
             centres and wraps them around the poles, where Mitsuba's rows
             are corner-aligned (row j at v = j / (H - 1)) and clamped; the
             two differ within a texel of the poles.  Its importance
             sampling differs too (unbiased either way).  An envmap given as
             an image array, not a file, is refused.
  depth      path.pathdepth.total = Mitsuba's max_depth, both counting the
             path's segments (an emitter seen directly: 1).  Found by
             rendering, not by LuxCore's documentation: the Cornell box's mean
             from LuxCore at total N matches Mitsuba's at max_depth N for N =
             2, 3 and 8 within the noise, and tests/bench/test_bench_luxcore.py
             checks it against ours at depth 3, where an off-by-one shows.
             LuxCore at total 1 still samples the lights at the first hit (as
             at total 2), so Mitsuba's max_depth 0 and 1 have no equivalent
             and are refused.  The diffuse / glossy / specular limits are set
             to the same number, so only the total binds.  Its accounting of
             specular bounces may differ in detail (the glass ball's region
             differs most at a small depth).
  roulette   path.russianroulette.depth = Mitsuba's rr_depth (5).  Approximate:
             LuxCore's survival probability is the last BSDF sample's weight
             clamped to [cap, 1] (cap ROULETTE_CAP) and it plays no roulette
             after a specular bounce; Mitsuba's is the path throughput times
             eta^2, at most 0.95.  Unbiased either way: it moves noise only.
  sampler    RANDOM (Mitsuba's independent sampler), box filter 1 pixel wide
             (film.filter.width 0.5 is its radius), uniform light choice
             (Mitsuba samples emitters uniformly), no clamping, no denoiser.
  film       the RGB output: linear radiance, rows bottom-up (flipped here).
"""
from __future__ import annotations

import atexit
import os
import time

import numpy as np

#: The roughness given to LuxCore's stand-in for a smooth conductor or plastic.
SMOOTH = 1e-3

#: LuxCore's lower bound on the Russian roulette survival probability (its default).
ROULETTE_CAP = 0.5

#: LuxCore's latitude-longitude frame in Mitsuba's envmap frame: the
#: direction (x, y, z) in Mitsuba's frame is (-z, x, y) in LuxCore's (its
#: u = atan2(y, x) / (2 pi) and top row +z against Mitsuba's
#: u = atan2(x, -z) / (2 pi) and top row +y), so LuxCore's light-to-world
#: transformation is to_world @ ENVMAP_FRAME.  A mirror: det -1.
ENVMAP_FRAME = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])

#: LuxCore's render threads: both of the machine's cores.
THREADS = 2


def available() -> str | None:
    """None when pyluxcore imports, else why not.  Asked of a child process:
    pyluxcore in the bench's own process aborts it once Mitsuba or the
    OpenCL runtimes load beside it."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, "-c", "import numpy, pyluxcore"],
                          capture_output=True, text=True)
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines()
        return lines[-1] if lines else f"exit status {done.returncode}"
    return None


def _pyluxcore():
    # Our EXR reader's OpenEXR module imported after pyluxcore (which bundles
    # OpenEXR libraries of its own) aborts the process ("free(): invalid
    # pointer") when a scene's envmap file is read: so it comes first.
    try:
        import OpenEXR  # noqa: F401
    except ImportError:
        pass
    import pyluxcore
    if not getattr(_pyluxcore, "started", False):
        pyluxcore.Init(_quiet)  # its log would flood the bench's output
        # a Python log handler left in place aborts the interpreter's exit
        atexit.register(pyluxcore.SetLogHandler, None)
        _pyluxcore.started = True
    return pyluxcore


def _quiet(message: str) -> None:
    """LuxCore's log handler: drops its lines."""


def _color(value) -> str:
    rgb = np.broadcast_to(np.asarray(value, np.float64), 3)
    return " ".join(repr(float(x)) for x in rgb)


def _ior(spec: dict, default_int: float, default_ext: float) -> tuple[float, float]:
    return float(spec.get("int_ior", default_int)), float(spec.get("ext_ior", default_ext))


def _roughness(spec: dict, prefix: str, alpha: float) -> list[str]:
    return [f"{prefix}.uroughness = {alpha!r}", f"{prefix}.vroughness = {alpha!r}"]


def material_lines(name: str, spec: dict) -> list[str]:
    """One of our material specs (hlbvh_cl.render.materials) as LuxCore
    scene.materials.<name>.* lines (see the module's list of what is
    approximate)."""
    while spec.get("type") == "twosided":
        spec = spec["bsdf"]
    kind, prefix = spec["type"], f"scene.materials.{name}"
    alpha = float(spec.get("alpha", 0.1))
    if kind == "diffuse":
        return [f"{prefix}.type = matte", f"{prefix}.kd = {_color(spec.get('reflectance', 0.5))}"]
    if kind in ("dielectric", "roughdielectric"):
        inside, outside = _ior(spec, 1.5046, 1.000277)
        lines = [f"{prefix}.type = {'glass' if kind == 'dielectric' else 'roughglass'}",
                 f"{prefix}.kr = {_color(spec.get('specular_reflectance', 1.0))}",
                 f"{prefix}.kt = {_color(spec.get('specular_transmittance', 1.0))}",
                 f"{prefix}.interiorior = {inside!r}", f"{prefix}.exteriorior = {outside!r}"]
        return lines + (_roughness(spec, prefix, alpha) if kind == "roughdielectric" else [])
    if kind in ("conductor", "roughconductor"):
        eta, k = spec.get("eta", 0.0), spec.get("k", 1.0)
        if spec.get("material", "none") != "none":
            from hlbvh_cl.render.metals import METALS
            eta, k = METALS[spec["material"]]
        return [f"{prefix}.type = metal2", f"{prefix}.n = {_color(eta)}",
                f"{prefix}.k = {_color(k)}",
                *_roughness(spec, prefix, alpha if kind == "roughconductor" else SMOOTH)]
    if kind in ("plastic", "roughplastic"):
        inside, outside = _ior(spec, 1.49, 1.000277)
        eta = inside / outside
        return [f"{prefix}.type = glossy2",
                f"{prefix}.kd = {_color(spec.get('diffuse_reflectance', 0.5))}",
                f"{prefix}.ks = {_color(((eta - 1) / (eta + 1)) ** 2)}",
                f"{prefix}.multibounce = 0",
                *_roughness(spec, prefix, alpha if kind == "roughplastic" else SMOOTH)]
    raise ValueError(f"{name}: material type {kind!r} is not translated to LuxCore yet")


def scene_properties(description, width: int, height: int) -> tuple[list[str], list]:
    """(LuxCore scene property lines, [(mesh name, Mesh)]) of a
    SceneDescription rendered at width x height (module docstring)."""
    camera = description.camera
    aspect, row = width / height, 2.0 / height  # one pixel in screen-window units
    lines = ["scene.camera.type = perspective",
             f"scene.camera.lookat.orig = {_color(camera.eye)}",
             f"scene.camera.lookat.target = {_color(camera.target)}",
             f"scene.camera.up = {_color(camera.up)}",
             f"scene.camera.fieldofview = {camera.fov_deg!r}",
             f"scene.camera.screenwindow = {-aspect!r} {aspect!r} {-1.0 - row!r} {1.0 - row!r}"]
    surfaces = description.surfaces()  # geom_id order; a sphere as its tessellation
    materials = description.materials() or [None] * len(surfaces)
    meshes = []
    for index, (entry, spec) in enumerate(zip(surfaces, materials)):
        name, mesh = f"m{index}", entry.mesh
        spec = spec or {"type": "diffuse", "reflectance": list(entry.color)}
        lines += material_lines(name, spec)
        if getattr(entry, "emitter", None) is not None:
            lines += [f"scene.materials.{name}.emission = {_color(entry.emitter['radiance'])}",
                      f"scene.materials.{name}.emission.gain = 1 1 1",
                      f"scene.materials.{name}.emission.power = 0",
                      f"scene.materials.{name}.emission.efficency = 0"]
        lines += [f"scene.objects.{name}.shape = {name}", f"scene.objects.{name}.material = {name}"]
        meshes.append((name, mesh))
    for index, emitter in enumerate(description.emitters):
        prefix = f"scene.lights.l{index}"
        if emitter["type"] == "constant":
            lines += [f"{prefix}.type = constantinfinite",
                      f"{prefix}.color = {_color(emitter['radiance'])}", f"{prefix}.gain = 1 1 1"]
        elif emitter["type"] == "point":
            lines += [f"{prefix}.type = point", f"{prefix}.position = {_color(emitter['position'])}",
                      f"{prefix}.color = {_color(emitter['intensity'])}",
                      f"{prefix}.gain = 1 1 1", f"{prefix}.power = 0", f"{prefix}.efficency = 0"]
        elif emitter["type"] == "directional":
            lines += [f"{prefix}.type = sharpdistant",
                      f"{prefix}.direction = {_color(emitter['direction'])}",
                      f"{prefix}.color = {_color(emitter['irradiance'])}", f"{prefix}.gain = 1 1 1"]
        elif emitter["type"] == "envmap":
            lines += envmap_lines(prefix, emitter, f"emitter {index} (envmap)")
        else:
            raise ValueError(f"emitter {index} ({emitter['type']!r}) is not translated to "
                             "LuxCore yet (constant, point, directional, envmap and area "
                             "emitters are)")
    return lines, meshes


def envmap_lines(prefix: str, emitter: dict, name: str) -> list[str]:
    """An envmap emitter spec as LuxCore infinite light lines (module
    docstring); errors name ``name``."""
    from hlbvh_cl.render.envmap import to_world_rotation
    if "filename" not in emitter:
        raise ValueError(f"{name}: an envmap given as an image array, not a file, is not "
                         "translated to LuxCore (LuxCore reads the map from its file)")
    filename = os.fspath(emitter["filename"])
    if '"' in filename:
        raise ValueError(f"{name}: the file name {filename!r} holds a double quote, which "
                         "LuxCore's scene properties cannot quote")
    to_world = to_world_rotation(f"{name}['to_world']", emitter.get("to_world"))
    frame = np.eye(4)
    frame[:3, :3] = to_world @ ENVMAP_FRAME
    # LuxCore's light-to-world matrix column by column (or, the same numbers
    # for an orthogonal matrix, its inverse row by row: rendering cannot tell)
    return [f"{prefix}.type = infinite", f'{prefix}.file = "{filename}"',
            f"{prefix}.gamma = 1.0", f"{prefix}.gain = {_color(emitter.get('scale', 1.0))}",
            f"{prefix}.transformation = " + " ".join(repr(float(x)) for x in frame.T.ravel())]


def config_properties(width: int, height: int, spp: int, max_depth: int, rr_depth: int,
                      seed: int = 1) -> list[str]:
    """LuxCore render configuration lines: PATHCPU on THREADS threads,
    width x height, spp samples per pixel, the depth and roulette mapping of
    the module's docstring."""
    if 0 <= max_depth < 2:
        raise ValueError(f"max_depth {max_depth}: LuxCore samples the lights at the first hit "
                         "whatever its path depth, so depths under 2 have no LuxCore equivalent")
    depth = int(max_depth) if max_depth >= 0 else 1 << 16  # -1: unbounded, as Mitsuba's
    return ["renderengine.type = PATHCPU", f"native.threads.count = {THREADS}",
            f"renderengine.seed = {seed}", "sampler.type = RANDOM",
            f"film.width = {width}", f"film.height = {height}",
            "film.filter.type = BOX", "film.filter.width = 0.5",
            "film.outputs.0.type = RGB", "film.outputs.0.filename = unused.exr",
            "film.imagepipelines.0.0.type = NOP",
            "lightstrategy.type = UNIFORM",
            f"path.pathdepth.total = {depth}", f"path.pathdepth.diffuse = {depth}",
            f"path.pathdepth.glossy = {depth}", f"path.pathdepth.specular = {depth}",
            f"path.russianroulette.depth = {int(rr_depth)}",
            f"path.russianroulette.cap = {ROULETTE_CAP!r}",
            "path.clamping.variance.maxvalue = 0",
            f"batch.haltspp = {int(spp)}", "batch.halttime = 0"]


class LuxCoreRenderer:
    """A SceneDescription as a LuxCore scene, parsed once; render() starts a
    render session for each image."""

    def __init__(self, description, width: int, height: int):
        lux = _pyluxcore()
        self.width, self.height = width, height
        lines, meshes = scene_properties(description, width, height)
        self.scene = lux.Scene()
        for name, mesh in meshes:
            normals = None if mesh.face_normals else np.ascontiguousarray(mesh.normals, np.float32)
            self.scene.DefineMeshExt(name, np.ascontiguousarray(mesh.vertices, np.float32),
                                     np.ascontiguousarray(mesh.faces, np.uint32), normals)
        self.scene.Parse(_properties(lux, lines))
        self.stats = {}

    def render(self, spp: int, max_depth: int, rr_depth: int = 5, seed: int = 1) -> np.ndarray:
        """A (height, width, 3) float32 linear image, top row first.
        self.stats: seconds (wall time from the session's Start returning --
        the scene compiled and the BVH built -- until the last sample is
        done), start_seconds (Start's own, left out), engine_seconds (LuxCore's own stats.renderengine.time) and
        samples (its sample count)."""
        lux = _pyluxcore()
        config = lux.RenderConfig(_properties(lux, config_properties(
            self.width, self.height, spp, max_depth, rr_depth, seed)), self.scene)
        session = lux.RenderSession(config)
        starting = time.perf_counter()
        session.Start()  # compiles the scene and builds its BVH, then starts the threads
        started = time.perf_counter()
        while not session.HasDone():
            time.sleep(0.002)
            session.UpdateStats()  # where LuxCore checks its halt conditions
        seconds = time.perf_counter() - started
        session.UpdateStats()
        stats = session.GetStats()
        film = session.GetFilm()
        image = np.zeros(self.width * self.height * 3, np.float32)
        film.GetOutputFloat(lux.FilmOutputType.RGB, image)
        session.Stop()
        self.stats = {"seconds": seconds, "start_seconds": started - starting,
                      "engine_seconds": stats.Get("stats.renderengine.time").GetFloat(),
                      "samples": stats.Get("stats.renderengine.pass").GetInt()
                      * self.width * self.height}
        return image.reshape(self.height, self.width, 3)[::-1].copy()  # rows bottom-up


def _properties(lux, lines: list[str]):
    properties = lux.Properties()
    properties.SetFromString("\n".join(lines) + "\n")
    return properties


def from_file(path, width: int, height: int) -> LuxCoreRenderer:
    """The scene file at ``path`` (read as bench.path's renderers read it,
    at width x height) as a LuxCoreRenderer."""
    from hlbvh_cl.io.scenefile import read
    description = read(os.fspath(path), {"res_x": width, "res_y": height})
    return LuxCoreRenderer(description, width, height)


# ---------------------------------------------------------------- a child process

#: The child's loop: one render per stdin line "path width height spp
#: max_depth rr_depth seed out" (out: an .npy file for the image, or -), one
#: JSON line of its stats and image mean per render.
_CHILD = r"""
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from bench import luxcore
renderers = {}
print(json.dumps({"ready": True}), flush=True)
for line in sys.stdin:
    path, width, height, spp, max_depth, rr_depth, seed, out = line.split()
    key = (path, int(width), int(height))
    if key not in renderers:
        renderers[key] = luxcore.from_file(*key)
    image = renderers[key].render(int(spp), int(max_depth), int(rr_depth), int(seed))
    if out != "-":
        np.save(out, image)
    print(json.dumps({**renderers[key].stats, "mean": float(image.mean())}), flush=True)
"""


class LuxCoreChild:
    """LuxCore in a child process that renders on request, as bench.path's
    Mitsuba child does: pyluxcore and Mitsuba abort when imported into one
    process in that order, and LuxCore's threads stay out of ours."""

    def __init__(self):
        import subprocess
        import sys
        from pathlib import Path
        root = str(Path(__file__).resolve().parent.parent)
        self.process = subprocess.Popen([sys.executable, "-c", _CHILD, root],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        text=True)
        self._answer("starting")

    def _answer(self, doing: str) -> dict:
        import json
        for line in self.process.stdout:
            if line.startswith("{"):  # pyluxcore prints its libraries on import
                return json.loads(line)
        raise RuntimeError(f"LuxCore's child process died {doing}")

    def render(self, path, width: int, height: int, spp: int, max_depth: int,
               rr_depth: int = 5, seed: int = 1, out="-") -> dict:
        """LuxCoreRenderer.render's stats and the image mean ("mean");
        the image saved to ``out`` unless it is "-"."""
        self.process.stdin.write(f"{path} {width} {height} {spp} {max_depth} {rr_depth} "
                                 f"{seed} {out}\n")
        self.process.stdin.flush()
        return self._answer(f"rendering {path}")

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait()


def start_child(paths: dict, max_depth: int) -> tuple[LuxCoreChild | None, str | None]:
    """A LuxCoreChild that has rendered each scene file of ``paths`` once
    (16x16, 1 spp), and None; or None and why LuxCore is left out: pyluxcore
    does not import, or its child died on one of them (pyluxcore 2.11 aborts
    with "double free or corruption" in RenderSession.Start on a 2-core Zen 4
    VM), so that a peer's crash costs the bench only its columns."""
    problem = available()
    if problem:
        return None, f"pyluxcore does not import: {problem}"
    child = LuxCoreChild()
    for path in paths.values():
        try:
            child.render(path, 16, 16, 1, max_depth)
        except RuntimeError as error:
            child.process.kill()
            return None, f"{error} (a 16x16 probe)"
    return child, None
