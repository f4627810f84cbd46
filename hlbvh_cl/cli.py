"""The ``hlbvh-cl`` command.

    hlbvh-cl devices                        list the OpenCL devices and their ids
    hlbvh-cl info SCENE.toml                load a scene file, build its BVH, print the stats
    hlbvh-cl render SCENE.toml -o out.png   render a scene file to an image, print the times
    hlbvh-cl render bunny.ply -o out.png    a mesh file alone: on a ground, framed
    hlbvh-cl --version

A user's mistake (a bad scene file or option, an unknown device) ends with a
one-line error and exit code 2, never a traceback; Ctrl-C with one line and
exit code 130.  A step that takes more than a second (a first run probes
devices and compiles kernels) says so on stderr.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import threading
import sys
import time
import warnings
from pathlib import Path

from . import __version__
from . import devices
from .io import scenefile
from .build.instances import InstancedTree
from .device.discovery import select_device, unregistered
from .device.runtime import DeviceMemoryError, KernelBuildError
from .render.camera import MAX_IMAGE_SIDE
from .render.integrators import SHADINGS
from .render.renderer import RenderInterrupted
from .render.settings import AO_SAMPLES, MAX_AO_SAMPLES, MAX_DEPTH, MAX_SPP

#: What a slow first run is doing (stage).
_PROBING = "probing the OpenCL devices in child processes (once per device and driver)"
_BUILDING = "loading the scene and building its BVH (kernels compile on a first run)"

_DEVICE_HELP = "device id, index, runtime (pocl, intel), type (cpu, gpu) or name (default: auto)"

#: Image formats the render command writes (through imageio).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".exr")


def device_state(d) -> str:
    """What the kernel probe found for a device, in one line."""
    if d.simulator:
        return f"a simulator: used only when named (device='{d.id}'), never by default"
    verdict = d.verdict
    if verdict.chosen is None:
        return f"cannot run kernels: {verdict.problem}"
    state = f"ok: kernels {verdict.chosen.name}"
    if verdict.mrays_per_s:
        state += f", {verdict.mrays_per_s:.1f} Mrays/s in the probe"
    for failed, reason in verdict.failures:
        state += f"; {failed.name} failed: {reason}"
    return state


def _cmd_devices(args) -> int:
    found = devices()
    if not found:
        print("no OpenCL device found; install PoCL: pip install pocl-binary-distribution")
        return 1
    for d in found:
        print(f"{d.id:10s} {d.type:4s} {d.name} [{d.platform}, driver {d.driver_version}, "
              f"{d.compute_units} compute units, profile {d.profile.name}] {device_state(d)}")
    for note in unregistered:
        print(f"not listed: {note}")
    usable = [d for d in found if d.skipped_because is None]
    print(f"default: {select_device().id if usable else 'none (no device runs the kernels)'}")
    if args.require:
        def passes(d):
            verdict = d.verdict
            return verdict.chosen is not None and not (args.no_fallback and verdict.failures)
        matching = [d for d in found if args.require in d.id and not d.simulator]
        if not any(passes(d) for d in matching):
            which = "runs its fastest kernel variant" if args.no_fallback else "runs kernels"
            print(f"hlbvh-cl: error: no device whose id contains {args.require!r} {which}",
                  file=sys.stderr)
            return 1
    return 0


def _counted(count: int, word: str) -> str:
    """'1 mesh', '2 meshes', '1 sphere', '3 spheres'."""
    return f"{count:,} {word}" + ("" if count == 1 else "es" if word.endswith("sh") else "s")


def _instances(scene) -> str:
    """An instanced scene in a few words: its instances, the triangles its
    meshes' trees hold and the triangles its instances place."""
    stored = sum(m.triangle_count for m in scene.meshes)
    placed = sum(scene.meshes[m].triangle_count for m in scene.instance_meshes)
    return (f"{len(scene.transforms):,} instances, {stored:,} triangles stored, "
            f"{placed:,} placed")


def _cmd_info(args) -> int:
    with stage(_PROBING):
        select_device(args.device)
    with stage(_BUILDING):  # nothing rendered: no render value is used
        loaded = scenefile.load(args.scene, args.device, args.builder, args.morton_bits,
                                replaced=("spp", "max_depth", "width", "height"),
                                compact=args.compact)
    Interrupts.check()
    scene = loaded.scene
    if args.repeat > 1:  # the first build pays for kernel compilation
        for _ in range(args.repeat - 1):
            scene.rebuild()
    s = scene.stats
    spheres = f", {_counted(len(scene.spheres), 'sphere')}" if len(scene.spheres) else ""
    print(f"scene      {loaded.path}  ({_counted(len(scene.meshes), 'mesh')}{spheres}, loaded in "
          f"{loaded.load_seconds:.2f} s)")
    if scene.transforms is not None:
        print(f"instances  {_instances(scene)}; the stats below are the top tree's, "
              "over the instances")
    print(f"device     {scene.device}")
    print(f"builder    {s.builder} ({s.morton_bits}-bit Morton codes, {s.clusters} clusters)")
    print(f"triangles  {s.triangles:,}")
    print(f"nodes      {s.nodes:,}   leaves {s.leaves:,}   depth {s.depth}   "
          f"(8-wide: {s.wide_nodes:,} nodes, depth {s.wide_depth})")
    # a two-level scene's stats are its top tree's, whose leaves are proxies, never
    # compact; its meshes' trees, which hold the triangles, get a line of their own
    with scene.borrow() as built:
        meshes = built.tree.meshes if isinstance(built.tree, InstancedTree) else None
    leaves = "compact leaves" if scene.compact else "leaf triangles"
    print(f"memory     {s.tree_bytes / 2**20:.2f} MiB on the device for traversal: nodes "
          f"{s.node_bytes:,} B + {leaves if meshes is None else 'leaf triangles'} "
          f"{s.triangle_bytes:,} B")
    if meshes is not None:
        held = meshes.memory()
        print(f"meshes     {sum(held.values()) / 2**20:.2f} MiB for the meshes' trees: nodes "
              f"{held['node_bytes']:,} B + {leaves} {held['triangle_bytes']:,} B")
    print(f"SAH cost   {s.sah_cost:.2f}  (C_t = C_i = 1, relative to the root's area)")
    stages = "  ".join(f"{k} {v:.1f}" for k, v in s.times_ms.items())
    print(f"build ms   {stages}")
    print(f"           device total {s.device_ms:.1f}, wall {s.wall_ms:.1f}")
    return 0


def _cmd_render(args) -> int:
    output = Path(args.output)
    if output.suffix.lower() not in IMAGE_SUFFIXES:
        raise ValueError(f"cannot write {output}: the file name must end in one of "
                         f"{', '.join(IMAGE_SUFFIXES)}")
    if not output.parent.is_dir():
        raise ValueError(f"cannot write {output}: folder {output.parent} does not exist")
    with stage(_PROBING):
        select_device(args.device)  # an unknown device fails before the scene loads
    started = time.perf_counter()
    # the file's values that a flag replaces, or that the render does not
    # use (a depth, shading other than path), may lie past the renderer's
    # limits (Mitsuba loads sample counts and film sizes this renderer does not)
    flags = {"spp": args.spp or args.time,
             "max_depth": args.max_depth is not None or args.shading not in (None, "path"),
             "width": args.width, "height": args.height}

    def not_an_input(description) -> None:  # before the build, which can take seconds
        for source in description.inputs():
            if _same_file(output, source):
                raise ValueError(f"cannot write {output}: the scene reads it ({source}); "
                                 "writing the image there would destroy it: choose another "
                                 "file")
    with stage(_BUILDING):
        loaded = scenefile.load(args.scene, args.device,
                                replaced={name for name, given in flags.items() if given},
                                check=not_an_input)
    Interrupts.check()
    scene, renderer = loaded.scene, loaded.renderer()
    build_wall = loaded.build_seconds
    width = args.width or loaded.width
    height = args.height or loaded.height
    camera = loaded.camera_at(width, height)  # a Mitsuba sensor's fov along its own axis
    # the file's own render options (a Mitsuba XML scene's), where no flag is given
    given = loaded.options
    shading = args.shading or given.get("shading", "diffuse")
    if args.max_depth is not None and shading != "path":
        raise ValueError(f"--max-depth applies to --shading path, not {shading}")
    spp = args.spp or (None if args.time else given.get("spp", 1))
    options = dict(shading=shading, shadows=not args.no_shadows, spp=spp,
                   ao_samples=args.ao_samples or AO_SAMPLES,
                   rfilter=given.get("rfilter", "box"), seed=given.get("seed", 0))
    if shading == "path":
        options.update(max_depth=args.max_depth if args.max_depth is not None
                       else given.get("max_depth", -1), rr_depth=given.get("rr_depth", 5))
    exr = output.suffix.lower() == ".exr"
    outputs = {"hdr": exr, "aovs": exr and shading == "path"}
    # A one-pixel render of one sample first: it compiles (or loads from the
    # cache) every kernel the render uses, so the real render's times are its
    # own; one sample, whatever --spp says, so that it takes no time of its own
    # and Ctrl-C finds the real render running.
    warm_started = time.perf_counter()
    with stage("compiling the render kernels (cached after a first run)"):
        renderer.render(camera, 1, 1, **{**options, "spp": 1}, **outputs)
    render_compile = time.perf_counter() - warm_started
    bar = sys.stderr.isatty()  # a tqdm bar on a terminal; else one line if it takes a while
    if args.time:
        options["time_budget"] = args.time
    try:
        with contextlib.nullcontext() if bar else stage(f"rendering {width}x{height}"):
            # a path render to EXR carries the AOVs as channels beside R, G, B
            image = renderer.render(camera, width, height, progress=bar, **outputs,
                                    **options)
    except RenderInterrupted as stopped:  # Ctrl-C: keep the rounds done
        _write_image(output, stopped.image)
        print(f"hlbvh-cl: interrupted after {stopped.spp} samples per pixel; wrote {output}",
              file=sys.stderr)
        return 130
    written_started = time.perf_counter()
    _write_image(output, image)
    written = time.perf_counter() - written_started
    spp = f"{renderer.stats['spp']} spp"
    if renderer.stats["mean_spp"] != renderer.stats["spp"]:  # a time budget's last round
        spp += f" ({renderer.stats['mean_spp']:.2f} on average)"

    build_ms = scene.stats.device_ms
    widen_ms = scene.stats.times_ms["widen"]  # the wide tree traversal reads
    bvh_ms = build_ms - widen_ms
    rendered = renderer.stats
    times = rendered["times_ms"]
    # Build kernels compile during the first build: its wall time beyond the
    # device time is that compilation (or cache loading) and host work.
    build_compile = max(0.0, build_wall - build_ms * 1e-3)
    described = shading + (" with shadows" if shading == "diffuse" and not args.no_shadows
                           else "")
    rays = f"{_count(rendered['primary_rays'])} primary"
    if rendered["secondary_rays"]:
        kind = {"ao": "AO", "path": "bounce and shadow"}.get(shading, "shadow")
        rays += f" + {_count(rendered['secondary_rays'])} {kind} rays"
    if scene.transforms is not None:
        print(f"scene        {loaded.path}: {_counted(len(scene.meshes), 'mesh')}, "
              f"{_instances(scene)} "
              "(build: the top tree's)")
    else:
        spheres = f", {_counted(len(scene.spheres), 'sphere')}" if len(scene.spheres) else ""
        print(f"scene        {loaded.path}: {_counted(len(scene.meshes), 'mesh')}, "
              f"{scene.stats.triangles:,} triangles{spheres}")
    print(f"device       {scene.device}")
    print(f"load         {loaded.load_seconds:7.2f} s   read, split and transform the meshes")
    print(f"build        {build_ms:7.1f} ms  device: BVH {bvh_ms:.1f} + wide tree {widen_ms:.1f} "
          f"(wall {build_wall * 1e3:.0f} ms)")
    print(f"trace+shade  {times['total']:7.1f} ms  device (wall {times['wall']:.0f} ms): "
          f"{width}x{height}, {described}, {spp}, {rays}")
    print(f"compile      {build_compile + render_compile:7.2f} s   kernels built or loaded from "
          f"the cache: build {build_compile:.2f} s (wall - device), render {render_compile:.2f} s "
          f"(a 1-pixel render)")
    print(f"write        {written:7.2f} s   {output}")
    print(f"total        {time.perf_counter() - started:7.2f} s")
    return 0


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"hlbvh-cl: warning: {message}", file=sys.stderr)


def _same_file(a: Path, b: Path) -> bool:
    """Whether paths a and b name one existing file."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # either missing (or unreadable): not a file read and written
        return False


class Interrupts:
    """Ctrl-C as a KeyboardInterrupt that is remembered: code that catches
    BaseException (trimesh's optional imports, while a scene loads) would
    swallow it, and the command ran to the end.  The command checks after
    such work (check) and stops there."""

    seen = False

    @classmethod
    def handle(cls, signum, frame):
        cls.seen = True
        raise KeyboardInterrupt

    @classmethod
    def check(cls) -> None:
        if cls.seen:
            raise KeyboardInterrupt


@contextlib.contextmanager
def stage(what: str, after_s: float = 1.0):
    """Says on stderr what the command is doing when a step takes longer
    than ``after_s`` (a first run probes devices and compiles kernels for
    minutes); quiet when it is quick.  Results stay on stdout."""
    timer = threading.Timer(after_s, lambda: print(f"hlbvh-cl: {what} ...", file=sys.stderr,
                                                   flush=True))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


def _count(n: int) -> str:
    return f"{n / 1e6:.2f}M" if n >= 1_000_000 else f"{n:,}"


def _write_image(path: Path, image) -> None:
    if path.suffix.lower() == ".exr":  # float32 linear RGB, as rendered, and any AOVs
        from .io.exr import write_exr
        if hasattr(image, "albedo"):  # a RenderResult
            write_exr(path, image.image, {"albedo": image.albedo, "normal": image.normal,
                                          "depth": image.depth})
        else:
            write_exr(path, image)
        return
    import imageio.v3 as iio
    try:
        iio.imwrite(path, image)
    except (OSError, ValueError) as error:
        raise ValueError(f"cannot write {path}: {error}") from None


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (its default prints the usage first)."""

    def error(self, message):
        raise _UsageError(message)


def _depth(text: str) -> int:
    """--max-depth: -1, or 1..MAX_DEPTH."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value != -1 and not 1 <= value <= MAX_DEPTH:
        raise argparse.ArgumentTypeError(f"expected -1 (no limit) or 1..{MAX_DEPTH}, got {value}")
    return value


def _seconds(text: str) -> float:
    """--time: a number of seconds > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a number of seconds > 0, got {text}")
    return value


def _integer_in(low: int, high: int):
    """An argparse type: an integer in [low, high]."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected an integer from {low} to {high}, "
                                             f"got {value}")
        return value
    return parse


def _check_combinations(args) -> None:
    """Refuses an option that the others make meaningless, rather than
    ignoring it."""
    if args.command == "devices" and args.no_fallback and not args.require:
        raise _UsageError("--no-fallback applies to --require ID, which is missing")
    if args.command == "render":
        # without --shading: a Mitsuba XML scene's is path, any other file's diffuse
        shading = args.shading or ("path" if args.scene.lower().endswith(".xml") else "diffuse")
        if args.ao_samples is not None and shading != "ao":
            raise _UsageError(f"--ao-samples applies to --shading ao, not {shading}")
        if args.max_depth is not None and shading != "path":
            raise _UsageError(f"--max-depth applies to --shading path, not {shading}")
        if args.time is not None and shading != "path":
            raise _UsageError(f"--time applies to --shading path, not {shading}")
        if args.no_shadows and shading != "diffuse":
            raise _UsageError(f"--no-shadows applies to --shading diffuse, not {shading}")


def main(argv=None) -> int:
    parser = _Parser(prog="hlbvh-cl", description=__doc__.split("\n\n")[0].replace("``", ""))
    parser.add_argument("--version", action="version", version=f"hlbvh-cl {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    listing = sub.add_parser("devices", help="list OpenCL devices")
    listing.add_argument("--require", metavar="ID", default=None,
                         help="exit 1 unless a working device's id contains ID (e.g. pocl)")
    listing.add_argument("--no-fallback", action="store_true",
                         help="with --require: the device must run its fastest kernel variant")
    listing.set_defaults(run=_cmd_devices)
    info = sub.add_parser("info", help="build a scene file's BVH and print its stats")
    info.add_argument("scene", help="a .toml scene file, or a mesh file (.ply, .obj, ...)")
    info.add_argument("--device", default=None, help=_DEVICE_HELP)
    info.add_argument("--builder", default="hlbvh", choices=["hlbvh", "lbvh"])
    info.add_argument("--morton-bits", type=int, default=30, choices=[30, 63])
    info.add_argument("--compact", action="store_true",
                      help="leaves as vertex indices: less device memory, slower rays "
                           "(docs/queries.md)")
    info.add_argument("--repeat", type=_integer_in(1, 1000), default=2,
                      help="builds to run; the stats are the last one's (default 2)")
    info.set_defaults(run=_cmd_info)
    render = sub.add_parser("render", help="render a scene or mesh file to an image (PNG, JPEG, ...)")
    render.add_argument("scene", help="a .toml scene file, or a mesh file (.ply, .obj, ...)")
    render.add_argument("-o", "--output", required=True, metavar="IMAGE",
                        help=f"image file to write ({', '.join(IMAGE_SUFFIXES)})")
    side = _integer_in(1, MAX_IMAGE_SIDE)
    render.add_argument("--width", type=side, default=None,
                        help="image width in pixels (default: the scene file's)")
    render.add_argument("--height", type=side, default=None,
                        help="image height in pixels (default: the scene file's)")
    render.add_argument("--device", default=None, help=_DEVICE_HELP)
    render.add_argument("--shading", default=None, choices=SHADINGS,
                        help="default: diffuse; path for a Mitsuba .xml scene")
    render.add_argument("--spp", type=_integer_in(1, MAX_SPP), default=None,
                        help="samples per pixel (default 1, or a Mitsuba scene's sample_count)")
    render.add_argument("--ao-samples", type=_integer_in(1, MAX_AO_SAMPLES), default=None,
                        help=f"with --shading ao: ambient-occlusion rays per sample "
                             f"(default {AO_SAMPLES})")
    render.add_argument("--no-shadows", action="store_true", help="diffuse shading without shadows")
    render.add_argument("--max-depth", type=_depth, default=None,
                        help="with --shading path: segments per path at most, -1 for no limit "
                             "(Mitsuba's max_depth; default -1, or a Mitsuba scene's)")
    render.add_argument("--time", type=_seconds, default=None, metavar="SECONDS",
                        help="with --shading path: render rounds of one sample per pixel while "
                             "they fit in SECONDS (at most --spp if given), then one over the "
                             "first rows that still fit")
    render.set_defaults(run=_cmd_render)
    try:
        args = parser.parse_args(argv)
        _check_combinations(args)
    except _UsageError as error:
        print(f"hlbvh-cl: error: {error}", file=sys.stderr)
        return 2
    except SystemExit as done:  # --help, --version
        return done.code or 0
    Interrupts.seen = False
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, Interrupts.handle) if main_thread else None
    try:
        with warnings.catch_warnings():  # one line each, not Python's source line
            warnings.showwarning = _show_warning
            return args.run(args)
    except (ValueError, TypeError, OSError, DeviceMemoryError, KernelBuildError,
            RuntimeError) as error:  # OSError: files (missing, unreadable, unwritable)
        print(f"hlbvh-cl: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hlbvh-cl: interrupted", file=sys.stderr)
        return 130  # 128 + SIGINT, as a shell reports it
    finally:
        if previous is not None:  # (None: a handler not set from Python, kept as it is)
            signal.signal(signal.SIGINT, previous)


if __name__ == "__main__":
    sys.exit(main())
