"""The integrator interface: how a built scene becomes the film, sample by
sample (Mitsuba 3's Integrator, pbrt-v4's), and the records the renderer
hands an integrator."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl


@dataclass(frozen=True)
class Band:
    """The image rows one pass renders, and how its kernels cover them: the
    2D range of pixel_in_pass (kernels/render: bands of TILE_ROWS rows in
    tile order), or one work-item per pixel in ray order (``count``)."""
    first_row: np.uint32
    rows: np.uint32
    width: int
    count: int
    tile_range: tuple[int, int]


@dataclass(frozen=True)
class Look:
    """What a render shows besides the geometry, checked: each integrator
    reads its part."""
    colors: np.ndarray      # float32 (G, 3): Renderer.colors (the direct integrator)
    light: object           # hlbvh_cl.render.light.Light (the direct integrator)
    materials: np.ndarray   # layout.PATH_MATERIAL (G,), no emission yet (materials.py)
    emitters: object        # hlbvh_cl.render.emitters.Emitters
    #: mesh -> float64 (T, 3, 3): the world triangles of each emitting mesh,
    #: every instance's where the scene has instances; for a sphere's geom_id
    #: (after the meshes') float64 (4,), its centre and radius
    emissive: dict
    #: mesh -> float64 (T, 3, 3) world shading normals at those triangles'
    #: corners, or None for a mesh with face normals
    emissive_normals: dict
    meshes: tuple = ()      # the scene's Meshes: their shading normals (the path integrator)
    #: float64 (K, 3, 3) per instance, the inverse transpose of its map's
    #: linear part (normals to the world), or None for a flat scene
    instance_maps: object = None
    #: the scene's world surface area (every instance's), which bounds the
    #: power an environment map delivers to it (the path integrator's light choice)
    surface_area: float = 0.0
    #: the instances' own materials: layout.PATH_MATERIAL records, no emission
    #: (materials.instance_material_table)
    instance_materials: object = None
    #: int32 per instance: its row of instance_materials, -1 for its mesh's
    #: material (none for a flat scene)
    instance_material_rows: object = None
    #: int32 per instance: its mesh (Scene.instance_meshes); None for a flat scene
    instance_meshes: object = None


@dataclass
class Step:
    """One sample of one band, as the renderer hands it to an integrator
    once the band's primary rays and their closest hits are on the device:
    the buffers, the queries' entry points, and the events and pacing the
    renderer keeps."""
    rt: object            # hlbvh_cl.device.runtime.Runtime
    query: object         # hlbvh_cl.query.rays.RayQuery: enqueue_intersect / enqueue_occluded
    tree: object          # the tree the rays are traced in (its frame)
    band: Band
    sample: int           # 0, 1, ... spp - 1: 0 starts the film's sums
    stream: int           # its random numbers' stream (RenderSettings.stream)
    rays: cl.Buffer       # Ray per pixel of the band, in ray order
    hits: cl.Buffer       # Hit per ray
    accum: cl.Buffer      # the film's float4 sums per pixel (Film)
    overflow: cl.Buffer   # int32: a traversal ran out of stack
    instances: object     # int32 per ray: the hit's instance, for an integrator that
                          # needs_instances (else None)
    events: dict          # stage name -> events, for the render's stats
    done: object          # done(event): a step of rays ended (pacing, progress)


class Integrator:
    """A way to render: it lists the ``modes`` it renders (the names
    Renderer.render's ``shading`` takes), and per render:

    - ``prepare(rt, settings, tree, look, pixels)``: its kernels,
      parameters and buffers for passes of ``pixels`` pixels (``look``: a
      Look);
    - ``shade(step)``: one sample of one band after its closest hits, adding
      to ``step.accum``;
    - ``passes(settings)``: the ray passes shade launches per sample (for
      progress);
    - ``radiance(settings)``: whether the mode's sums are radiance, which
      the film gamma-encodes, or data it encodes as it is (Film.encode);
    - ``buffer_sizes(pixels)``: the bytes its buffers take, for the
      allocation check;
    - ``progressive``: whether it renders a sample over the whole image at
      a time (to a time budget, Ctrl-C keeping the rounds done) rather
      than every sample of a band at a time.
    """

    modes: tuple[str, ...] = ()
    progressive = False

    #: Whether shade reads each hit's instance (Step.instances).
    needs_instances = False

    def prepare(self, rt, settings, tree, look: Look, pixels: int) -> None:
        raise NotImplementedError

    def shade(self, step: Step) -> None:
        raise NotImplementedError

    def passes(self, settings) -> int:
        raise NotImplementedError

    def radiance(self, settings) -> bool:
        raise NotImplementedError

    def buffer_sizes(self, pixels: int) -> dict[str, int]:
        return {}
