"""Triangle meshes: validated numpy arrays, and loading them from files.

A Mesh owns two read-only, C-contiguous arrays: ``vertices`` (N, 3) float32
and ``faces`` (M, 3) int32, the layout every kernel reads, and the shading
normals the path integrator interpolates: ``normals`` (N, 3) float32, the
file's or the caller's where given, else computed as Mitsuba 3 computes them
(vertex_normals), unless ``face_normals`` is set.  Everything is
checked once here so that later stages can trust the arrays: bad input gives a
ValueError/TypeError that names the array, the first offending row and what
was expected.  Zero-area triangles are valid (ray queries never hit them).

Files are read through trimesh only (PLY, OBJ, OFF, STL, GLB, each optionally
gzip-compressed as ``name.ply.gz``); vertex and face order are kept.
"""
from __future__ import annotations

import errno
import gzip
import io
import os
import re
import warnings
import zlib
from pathlib import Path

import numpy as np

from .core import inputs

#: file extensions Mesh.load understands (each may also end in .gz)
MESH_EXTENSIONS = ("ply", "obj", "off", "stl", "glb")


#: An OBJ's material lines.  trimesh splits an OBJ at each ``usemtl`` into
#: parts, each with its own copy of the vertices and the faces regrouped by
#: material; without them the file is one part in its own order.
_OBJ_MATERIALS = re.compile(rb"(?m)^[ \t]*(?:usemtl|mtllib)\b[^\r\n]*")

#: An OBJ face line with a vertex index of 0 (OBJ counts from 1, or back
#: from -1), which trimesh would read as the first vertex.
_OBJ_ZERO_INDEX = re.compile(rb"(?m)^[ \t]*f[ \t](?:[^\r\n#]*?[ \t])?[+-]?0+(?=[/ \t\r]|$)")


class Mesh:
    """An indexed triangle mesh.

    vertices: (N, 3) array of any real float (or integer) dtype, stored as
    float32; faces: (M, 3) integer vertex indices, stored as int32.  Lists
    are accepted.  Both arrays are copied and stored read-only.

    ``Mesh(other)`` takes the arrays of another library's triangle mesh: a
    trimesh.Trimesh (``vertices``, ``faces``) or an Open3D TriangleMesh
    (``vertices``, ``triangles``).

    Shading (Mitsuba 3's rules, read by the path integrator only):
    ``normals`` (N, 3), one per vertex, not necessarily unit, or None to
    compute them (vertex_normals); ``face_normals=True`` shades with each
    triangle's geometric normal instead, as Mitsuba's ``face_normals``.
    """

    def __init__(self, vertices, faces=None, name: str | None = None, normals=None,
                 face_normals: bool = False):
        if faces is None:
            vertices, faces = _mesh_arrays(vertices)
        self._vertices = inputs.mesh_vertices(vertices)
        self._faces = inputs.mesh_faces(faces, len(self._vertices))
        inputs.check_mesh_scale(vertices, self._faces)
        self.name = name
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None
        self._area: float | None = None
        if not isinstance(face_normals, (bool, np.bool_)):
            raise TypeError(f"face_normals must be True or False, got "
                            f"{type(face_normals).__name__}")
        self.face_normals = bool(face_normals)
        self._given_normals = normals is not None
        self._normals = None if normals is None else _check_normals(normals, self.vertex_count)

    def __reduce__(self):
        """Pickles as its arrays, name and shading (checked again on arrival)."""
        given = self._normals if self._given_normals else None
        return (Mesh, (self._vertices, self._faces, self.name, given, self.face_normals))

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) float32 per-vertex shading normals, read-only: the given
        ones, or vertex_normals(vertices, faces) computed once."""
        if self._normals is None:
            computed = vertex_normals(self._vertices, self._faces).astype(np.float32)
            computed.flags.writeable = False
            self._normals = computed
        return self._normals

    @property
    def has_file_normals(self) -> bool:
        """Whether the normals were given (by the caller or the file) rather
        than computed."""
        return self._given_normals

    @property
    def vertices(self) -> np.ndarray:
        """(N, 3) float32, C-contiguous, read-only."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray:
        """(M, 3) int32, C-contiguous, read-only."""
        return self._faces

    @property
    def vertex_count(self) -> int:
        return int(self._vertices.shape[0])

    @property
    def triangle_count(self) -> int:
        return int(self._faces.shape[0])

    @property
    def area(self) -> float:
        """The triangles' total area, summed in float64 and computed once
        (a Mesh never changes)."""
        if self._area is None:
            total, chunk = 0.0, 1 << 18  # faces at a time: bounded scratch memory
            for start in range(0, self.triangle_count, chunk):
                corners = self._vertices[self._faces[start:start + chunk]].astype(np.float64)
                normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
                total += 0.5 * float(np.sqrt((normal * normal).sum(axis=1)).sum())
            self._area = total
        return self._area

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) float64 corners of the box around the vertices the faces use."""
        if self._bounds is None:
            used = np.zeros(self.vertex_count, dtype=bool)
            used[self._faces.ravel()] = True
            points = self._vertices[used]
            self._bounds = (points.min(axis=0).astype(np.float64),
                            points.max(axis=0).astype(np.float64))
        lo, hi = self._bounds
        return lo.copy(), hi.copy()

    def __repr__(self) -> str:
        label = f"{self.name!r}, " if self.name else ""
        return f"Mesh({label}{self.triangle_count} triangles, {self.vertex_count} vertices)"

    @classmethod
    def load(cls, path) -> "Mesh":
        """Read a PLY, OBJ, OFF, STL or GLB file (or any of them as ``.gz``).

        Vertex and face order are kept where the format allows: an STL's
        vertices may be merged, and a PLY or OFF file that mixes triangles
        with larger polygons lists its triangles first, then the others, each
        split into a fan (trimesh groups faces by size).  An OBJ keeps both
        orders whatever its materials; where its faces' corners give a vertex
        more than one texture coordinate or normal (a hard edge, a UV seam),
        that vertex gets a row for each, as Mitsuba 3's loader makes them (its
        first in the file's row, the others after the file's rows), so that
        it shades as in Mitsuba.  A file with several meshes (a GLB
        scene, an OBJ with several objects) becomes one mesh, with each part's
        transform applied.  Vertex normals the file stores (a PLY's nx, ny,
        nz; an OBJ's vn) become ``normals``, normalised as Mitsuba's
        loaders normalise them, where every part has them; else
        they are computed (vertex_normals).
        """
        path = Path(os.fspath(path))
        if path.is_dir():
            raise ValueError(f"{path}: is a folder, not a mesh file")
        file_type, gzipped = _file_type(path)
        if not path.is_file():
            raise FileNotFoundError(errno.ENOENT, "mesh file not found", str(path))
        vertices, faces, normals = _read_with_trimesh(path, file_type, gzipped)
        name = path.name[: -len(".gz")] if gzipped else path.name
        try:
            return cls(vertices, faces, name=name.rsplit(".", 1)[0],
                       normals=None if normals is None else unit_rows(normals))
        except (ValueError, TypeError) as error:
            raise ValueError(f"{path}: {error}") from None


def unit_rows(normals) -> np.ndarray:
    """float64 ``normals`` (N, 3), each divided by its length (a zero row
    stays zero, for Mesh to refuse): Mitsuba's mesh loaders normalise a
    file's vertex normals, after to_world, before they are interpolated,
    so a file's lengths weigh nothing."""
    rows = np.asarray(normals, np.float64)
    lengths = np.linalg.norm(rows, axis=1, keepdims=True)
    return np.divide(rows, lengths, out=np.zeros_like(rows), where=lengths > 0)


def vertex_normals(vertices, faces) -> np.ndarray:
    """Mitsuba 3's computed vertex normals (Mesh::recompute_vertex_normals),
    float64 (N, 3): each triangle adds its unit geometric normal
    cross(v1 - v0, v2 - v0) to its three corners, weighted by the corner's
    interior angle (Thuermer & Wuethrich 1998, "Computing Vertex Normals from
    Polygonal Facets"); zero-area triangles add nothing, and a vertex that
    gets nothing takes Mitsuba's stand-in (1, 0, 0)."""
    p = np.asarray(vertices, np.float64)[np.asarray(faces)]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(normal, axis=1)
    valid = length > 0
    normal[valid] /= length[valid, None]
    total = np.zeros((len(vertices), 3))
    for k in range(3):
        a = p[:, (k + 1) % 3] - p[:, k]
        b = p[:, (k + 2) % 3] - p[:, k]
        with np.errstate(invalid="ignore", divide="ignore"):
            a /= np.linalg.norm(a, axis=1)[:, None]
            b /= np.linalg.norm(b, axis=1)[:, None]
        angle = _unit_angle(a, b)
        keep = valid & np.isfinite(angle)
        np.add.at(total, np.asarray(faces)[keep, k], normal[keep] * angle[keep, None])
    length = np.linalg.norm(total, axis=1)
    out = np.tile([1.0, 0.0, 0.0], (len(vertices), 1))
    out[length > 0] = total[length > 0] / length[length > 0, None]
    return out


def _unit_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angle between unit rows a and b, accurate near 0 and pi as
    Mitsuba's unit_angle: 2 asin(|a - b| / 2), or pi minus that of -b."""
    dot = np.einsum("ij,ij->i", a, b)
    near = 2.0 * np.arcsin(np.minimum(1.0, 0.5 * np.linalg.norm(a - b, axis=1)))
    far = np.pi - 2.0 * np.arcsin(np.minimum(1.0, 0.5 * np.linalg.norm(a + b, axis=1)))
    return np.where(dot >= 0, near, far)


def _check_normals(normals, count: int) -> np.ndarray:
    """Per-vertex normals as Mesh stores them: (count, 3) float32, finite,
    read-only; errors name the first bad row."""
    # read as vertices are (inputs.as_array): masked entries, ragged rows,
    # strings and None refused by name rather than converted
    array = inputs.as_array("normals", normals)
    if array.dtype.kind not in "fiu":
        raise TypeError(f"normals has dtype {array.dtype}, expected real numbers (float32 "
                        f"preferred; any float or integer dtype is converted)")
    if array.ndim != 2 or array.shape != (count, 3):
        raise ValueError(f"normals has shape {array.shape}, expected ({count}, 3): one per vertex")
    with np.errstate(over="ignore"):  # overflow: named below
        converted = np.array(array, dtype=np.float32, order="C", copy=True)
    bad = ~np.isfinite(converted).all(axis=1) | ~(np.abs(converted).max(axis=1) > 0)
    if bad.any():
        row = int(np.argmax(bad))
        raise ValueError(f"normals[{row}] = {array[row].tolist()} is not a finite, nonzero "
                         f"vector in float32 (|x| <= {np.finfo(np.float32).max:.3g}, not all 0)")
    converted.flags.writeable = False
    return converted


def _mesh_arrays(mesh) -> tuple:
    """(vertices, faces) of another library's mesh object, for Mesh(mesh)."""
    kind = type(mesh).__name__
    if kind == "Scene" and hasattr(mesh, "dump"):  # trimesh.Scene: several meshes, placed
        raise TypeError("Mesh(mesh) got a trimesh.Scene, which holds several meshes: pass "
                        "scene.to_geometry() (trimesh >= 4.4) or scene.dump(concatenate=True), "
                        "or read the file with hlbvh_cl.Mesh.load")
    for faces_name in ("faces", "triangles"):  # trimesh, Open3D
        if hasattr(mesh, "vertices") and hasattr(mesh, faces_name):
            return mesh.vertices, getattr(mesh, faces_name)
    raise TypeError(f"Mesh(vertices, faces) is missing faces; one argument alone must be a mesh "
                    f"object with vertices and faces (a trimesh.Trimesh) or vertices and "
                    f"triangles (an Open3D TriangleMesh), got {kind}")


def _file_type(path: Path) -> tuple[str, bool]:
    suffixes = [s.lower() for s in path.suffixes]
    gzipped = bool(suffixes) and suffixes[-1] == ".gz"
    if gzipped:
        suffixes = suffixes[:-1]
    extension = suffixes[-1][1:] if suffixes else ""
    if extension not in MESH_EXTENSIONS:
        known = ", ".join("." + e for e in MESH_EXTENSIONS)
        raise ValueError(f"{path}: unknown mesh file extension {('.' + extension) if extension else '(none)'}"
                         f"{'.gz' if gzipped else ''}; expected one of {known}, "
                         f"optionally followed by .gz")
    return extension, gzipped


def _read_with_trimesh(path: Path, file_type: str, gzipped: bool) -> tuple:
    import trimesh  # imported here: only file loading needs it

    try:
        if gzipped:
            with gzip.open(path, "rb") as compressed:
                source = io.BytesIO(compressed.read())
        else:
            source = io.BytesIO(path.read_bytes())
    except (OSError, EOFError, zlib.error) as error:  # zlib: a corrupt .gz
        raise ValueError(f"{path}: cannot read the file: {error}") from None
    except MemoryError:
        raise ValueError(f"{path}: too large to read into this process's memory "
                         f"({path.stat().st_size:,} bytes on disk)") from None
    if file_type == "obj":
        source = io.BytesIO(_obj_geometry(path, source.getvalue()))
    stores_normals = _stores_normals(source.getvalue(), file_type)
    try:
        # maintain_order: an OBJ's vertex rows as the file lists them, unused
        # ones too, not renumbered by first use
        keep = {"maintain_order": True} if file_type == "obj" else {}
        with warnings.catch_warnings():  # trimesh's texture code warns on some OBJs' vt
            warnings.simplefilter("ignore", RuntimeWarning)
            scene = trimesh.load_scene(source, file_type=file_type, process=False, **keep)
        parts, normals = _placed_parts(scene, trimesh.Trimesh, stores_normals)
        if file_type == "obj" and _has_corner_attributes(source.getvalue()):
            parts, normals = _obj_corners_split(trimesh, source, parts, normals, stores_normals)
    except Exception as error:  # trimesh raises many types for malformed files
        reason = str(error) or type(error).__name__
        raise ValueError(f"{path}: trimesh cannot read it as {file_type.upper()}: {reason}") from None
    declared = _ply_element_counts(source.getvalue()) if file_type == "ply" else {}
    read = {"vertex": sum(len(p.vertices) for p in parts), "face": sum(len(p.faces) for p in parts)}
    # a polygon is one triangle or more: fewer than the header's count means
    # trimesh stopped early (it does on a cut ASCII PLY, and says nothing)
    if declared.get("face", 0) > 0 and any(read[name] < declared.get(name, 0) for name in read):
        faces, vertices = declared.get("face", 0), declared.get("vertex", 0)
        raise ValueError(f"{path}: its PLY header declares {faces:,} face{'s' * (faces != 1)} "
                         f"and {vertices:,} vertices, but trimesh read {read['face']:,} "
                         f"triangle{'s' * (read['face'] != 1)} and {read['vertex']:,} vertices: "
                         "the file is cut short or its header's counts are wrong")
    if not parts:
        raise ValueError(f"{path}: the file holds no triangles")
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    vertices = np.concatenate([np.asarray(p.vertices) for p in parts])
    faces = np.concatenate([np.asarray(p.faces, dtype=np.int64) + o for p, o in zip(parts, offsets)])
    if not all(n is not None for n in normals):
        return vertices, faces, None
    normals = np.concatenate(normals)
    # a row no face uses (an OBJ's stray v) may have no normal (trimesh gives
    # it zeros, which Mesh refuses): the stand-in Mitsuba gives a vertex
    # without one
    unused = np.ones(len(vertices), bool)
    unused[faces.ravel()] = False
    missing = unused & ~(np.isfinite(normals).all(axis=1) & (np.abs(normals).sum(axis=1) > 0))
    normals[missing] = [1.0, 0.0, 0.0]
    return vertices, faces, normals


def _placed_parts(scene, kind, stores_normals: bool) -> tuple[list, list]:
    """A trimesh scene's triangle meshes with each node's transform applied
    (as scene.dump() does), and, where the file stores vertex normals, each
    part's, mapped by the inverse transpose (None where it has none).
    trimesh computes normals lazily when a file has none, so whether it has
    them is read from the file itself (_stores_normals)."""
    parts, normals = [], []
    for node in scene.graph.nodes_geometry:
        matrix, name = scene.graph[node]
        geometry = scene.geometry[name]
        if not isinstance(geometry, kind) or not len(geometry.faces):
            continue
        stored = np.array(geometry.vertex_normals, np.float64) if stores_normals else None
        placed = geometry.copy()
        placed.apply_transform(matrix)
        parts.append(placed)
        if stored is not None and len(stored) == len(placed.vertices):
            stored = stored @ np.linalg.inv(np.asarray(matrix, np.float64)[:3, :3])
        else:
            stored = None
        normals.append(stored)
    return parts, normals


def _has_corner_attributes(data: bytes) -> bool:
    """Whether an OBJ lists texture coordinates or normals (vt, vn lines),
    which its faces' corners index apart from their vertices."""
    return re.search(rb"(?m)^[ \t]*v[tn][ \t]", data) is not None


def _obj_corners_split(trimesh, source: io.BytesIO, parts: list, normals: list,
                       stores_normals: bool) -> tuple[list, list]:
    """An OBJ read as Mitsuba 3 reads it where its corners give a vertex
    more than one (texture coordinate, normal) pair (a hard edge's normals,
    a UV seam): one vertex for each distinct combination, each with its own
    normal, given or computed over the faces that use it, so that the
    shading is Mitsuba's.  trimesh splits them so without maintain_order;
    here each file row keeps its place, its first combination in it, and
    the others follow the file's rows in the order the faces first use them.
    An OBJ whose vertices each keep one pair is returned as it was read
    (``parts``, ``normals``: the ordered read)."""
    source.seek(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        scene = trimesh.load_scene(source, file_type="obj", process=False)
    split, split_normals = _placed_parts(scene, trimesh.Trimesh, stores_normals)
    if sum(len(p.vertices) for p in split) <= sum(len(np.unique(np.asarray(p.faces)))
                                                   for p in parts):
        return parts, normals
    if len(split) != len(parts) or any(len(a.faces) != len(b.faces) for a, b in zip(split, parts)):
        return split, split_normals  # trimesh's two reads differ: its split as it is
    out, out_normals = [], []
    for ordered, ordered_normals, cut, cut_normals in zip(parts, normals, split, split_normals):
        rows, corners = np.asarray(ordered.faces).ravel(), np.asarray(cut.faces).ravel()
        if not np.array_equal(np.asarray(ordered.vertices)[rows],
                              np.asarray(cut.vertices)[corners]):
            return split, split_normals
        # the split vertex at each corner, and the file row it copies
        first = np.unique(corners, return_index=True)[1]
        order = np.sort(first)  # split vertices by their first use
        row_of = rows[order]
        # a row's first split vertex takes the row; the others follow the rows
        leads = np.zeros(len(order), bool)
        leads[np.unique(row_of, return_index=True)[1]] = True
        placed_at = np.where(leads, row_of, 0)
        placed_at[~leads] = len(ordered.vertices) + np.arange(int((~leads).sum()))
        vertex_of = np.full(len(cut.vertices), -1, np.int64)
        vertex_of[corners[order]] = placed_at
        extra = len(ordered.vertices) + int((~leads).sum())
        vertices = np.empty((extra, 3))
        vertices[:len(ordered.vertices)] = ordered.vertices
        vertices[vertex_of[vertex_of >= 0]] = np.asarray(cut.vertices)[vertex_of >= 0]
        out.append(trimesh.Trimesh(vertices, vertex_of[corners].reshape(-1, 3), process=False))
        if cut_normals is None:
            out_normals.append(None)
        else:
            placed = np.empty((extra, 3))
            placed[:len(ordered.vertices)] = (ordered_normals if ordered_normals is not None
                                              else [1.0, 0.0, 0.0])
            placed[vertex_of[vertex_of >= 0]] = cut_normals[vertex_of >= 0]
            out_normals.append(placed)
    return out, out_normals


def _stores_normals(data: bytes, file_type: str) -> bool:
    """Whether a PLY's vertex element has nx, ny, nz, or an OBJ has vn lines."""
    if file_type == "obj":
        return re.search(rb"(?m)^[ \t]*vn[ \t]", data) is not None
    if file_type == "ply":
        end = data.find(b"end_header", 0, 1 << 16)
        header = data[:max(end, 0)].decode("ascii", "replace").split("element")
        vertex = [part for part in header if part.split()[:1] == ["vertex"]]
        return bool(vertex) and all(re.search(rf"(?m)^property\s+\w+\s+{axis}\s*$",
                                              vertex[0]) for axis in ("nx", "ny", "nz"))
    return False


def _obj_geometry(path: Path, data: bytes) -> bytes:
    """An OBJ's text as trimesh should read it: without its material lines
    (_OBJ_MATERIALS), after refusing a face with vertex index 0."""
    zero = _OBJ_ZERO_INDEX.search(data)
    if zero:
        line = data.count(b"\n", 0, zero.start()) + 1
        end = data.find(b"\n", zero.start())
        text = data[zero.start():end if end >= 0 else len(data)]
        text = text.decode("utf-8", "replace").split("#")[0].strip()
        raise ValueError(f"{path}: line {line}: {text!r} has vertex index 0; OBJ indices count "
                         "from 1 (or back from -1 for the last vertex)")
    return _OBJ_MATERIALS.sub(b"", data)


def _ply_element_counts(data: bytes) -> dict[str, int]:
    """The element counts a PLY header declares ({"vertex": n, "face": m}),
    or {} where the header cannot be read."""
    end = data.find(b"end_header", 0, 1 << 16)
    if not data.startswith(b"ply") or end < 0:
        return {}
    counts = {}
    for line in data[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == "element" and words[2].isdigit():
            counts[words[1]] = int(words[2])
    return counts
