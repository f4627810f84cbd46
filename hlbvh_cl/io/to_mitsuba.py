"""A TOML scene file as Mitsuba 3's XML, for rendering one scene in both
renderers (bench/path.py, tests/io/test_mitsuba_xml.py): each mesh as
placed (split parts joined) written as a PLY beside the XML, its material
and area emitter, the file's other emitters, and the camera as a
``lookat`` with the same vertical field of view.  What Mitsuba's reader
(mitsuba.py) takes back, it reads as the TOML file's scene."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..render.emitters import DEFAULT
from .scenefile import read

#: Emitters of no shape, and the parameters each writes.
_EMITTERS = {"constant": ("radiance",), "point": ("position", "intensity"),
             "directional": ("direction", "irradiance")}


def _value(name: str, value) -> str:
    if isinstance(value, bool):
        return f'<boolean name="{name}" value="{str(value).lower()}"/>'
    if isinstance(value, str):
        return f'<string name="{name}" value="{value}"/>'
    if isinstance(value, (list, tuple, np.ndarray)):
        kind = "point" if name in ("position",) else "vector" if name == "direction" else "rgb"
        text = ", ".join(f"{float(v):.9g}" for v in value)
        return f'<{kind} name="{name}" value="{text}"/>'
    return f'<float name="{name}" value="{float(value):.9g}"/>'


def _bsdf(spec: dict) -> str:
    if spec["type"] == "twosided":
        return f'<bsdf type="twosided">{_bsdf(spec["bsdf"])}</bsdf>'
    body = "".join(_value(k, v) for k, v in spec.items() if k != "type")
    return f'<bsdf type="{spec["type"]}">{body}</bsdf>'


def write_xml(toml_path, folder, max_depth: int = 8, spp: int = 4, rfilter: str = "box",
              face_normals: bool = True) -> Path:
    """``toml_path`` as ``folder``/NAME.xml with its meshes as meshK.ply
    beside it; the film's size is $res_x x $res_y (defaults: the file's).
    ``face_normals`` is every shape's.  A file without materials gives each
    mesh the two-sided diffuse of its colour, and one without emitters the
    constant sky of 1 that lights it in this renderer; instances are
    refused (not written yet)."""
    import trimesh
    toml_path, folder = Path(toml_path), Path(folder)
    description = read(toml_path)
    if description.instances:
        raise ValueError(f"{toml_path}: [[instance]] placements are not written as XML yet")
    entries = description.surfaces()
    materials = description.materials() or [
        {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": list(entry.color)}}
        for entry in entries]
    emitters = description.all_emitters()
    if emitters is None:  # the renderer's default sky
        emitters = list(DEFAULT)
    entries = list(description.meshes) + ([description.ground] if description.ground else [])
    shapes = []
    for k, entry in enumerate(entries):
        mesh = entry.mesh
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(folder / f"mesh{k}.ply")
        emitter = next((e for e in emitters if e["type"] == "area" and e.get("mesh") == k), None)
        light = (f'<emitter type="area">{_value("radiance", emitter["radiance"])}</emitter>'
                 if emitter else "")
        normals = '<boolean name="face_normals" value="true"/>' if face_normals else ""
        shapes.append(f'<shape type="ply"><string name="filename" value="mesh{k}.ply"/>'
                      f'{normals}{_bsdf(materials[k])}{light}</shape>')
    others = []
    for e in emitters:
        if e["type"] in _EMITTERS:
            body = "".join(_value(key, e[key]) for key in _EMITTERS[e["type"]] if key in e)
            others.append(f'<emitter type="{e["type"]}">{body}</emitter>')
        elif e["type"] != "area":
            raise ValueError(f"{toml_path}: emitter type {e['type']!r} is not written as XML yet")
    camera = description.camera
    text = f"""<scene version="3.0.0">
  <default name="res_x" value="{description.width}"/>
  <default name="res_y" value="{description.height}"/>
  <default name="spp" value="{spp}"/>
  <integrator type="path"><integer name="max_depth" value="{max_depth}"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="{camera.fov_deg}"/><string name="fov_axis" value="y"/>
    <transform name="to_world"><lookat origin="{', '.join(map(str, camera.eye))}"
      target="{', '.join(map(str, camera.target))}" up="{', '.join(map(str, camera.up))}"/>
    </transform>
    <film type="hdrfilm"><integer name="width" value="$res_x"/>
      <integer name="height" value="$res_y"/><rfilter type="{rfilter}"/></film>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
  </sensor>
  {''.join(shapes)}
  {''.join(others)}
</scene>
"""
    path = folder / f"{toml_path.stem}.xml"
    path.write_text(text)
    return path
