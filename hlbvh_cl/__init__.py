"""hlbvh_cl: HLBVH construction and ray queries on any OpenCL device.

    import hlbvh_cl
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh.load("bunny.ply")], device="pocl")
    hits = scene.intersect(origins, directions)       # closest hit
    blocked = scene.occluded(origins, directions)     # any hit
    scene.update_vertices(0, moved_vertices)          # refit on the device
    image = scene.render(hlbvh_cl.Camera(eye, target), 640, 480)   # (480, 640, 3) uint8
"""
from .device import Device, DeviceMemoryError, KernelBuildError, devices
from .mesh import Mesh
from .query import Hits
from .render import Camera, Light
from .scene import Scene

__all__ = ["Camera", "Device", "DeviceMemoryError", "Hits", "KernelBuildError", "Light", "Mesh",
           "Scene", "devices"]
__version__ = "0.1.0"
