"""hlbvh_cl: HLBVH construction and ray queries on any OpenCL device.

    import hlbvh_cl
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh.load("bunny.ply")], device="pocl")
    hits = scene.intersect(origins, directions)       # closest hit
    blocked = scene.occluded(origins, directions)     # any hit
    nearest = scene.closest_points(points)            # closest surface points
    sdf = scene.signed_distance(points)               # negative inside
    every = scene.intersect_all(origins, directions)  # all hits, sorted by t (AllHits)
    scene.update_vertices(0, moved_vertices)          # refit on the device
    camera = hlbvh_cl.Camera(eye, target)
    image = hlbvh_cl.Renderer(scene).render(camera, 640, 480)   # (480, 640, 3) uint8
    loaded = hlbvh_cl.io.scenefile.load("scenes/reference.toml")   # a scene file, built
"""
from .io import scenefile
from .query.all_hits import AllHits
from .build.pipeline import BuildStats
from .device.discovery import Device, devices
from .device.runtime import DeviceMemoryError, KernelBuildError
from .mesh import Mesh
from .query.points import ClosestPoints
from .query.rays import Hits
from .render.camera import Camera
from .render.light import Light
from .render.renderer import RenderInterrupted, Renderer, RenderResult
from .scene import Scene

__all__ = ["AllHits", "BuildStats", "Camera", "ClosestPoints", "Device", "DeviceMemoryError",
           "Hits", "KernelBuildError", "Light", "Mesh", "RenderInterrupted", "RenderResult",
           "Renderer", "Scene",
           "devices", "scenefile"]
__version__ = "0.1.0"
