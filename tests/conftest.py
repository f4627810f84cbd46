"""The suite runs on PoCL's CPU device unless HLBVH_CL_DEVICE says otherwise,
and every tree any test builds or refits gets its invariants checked."""
import os

import pytest

os.environ.setdefault("HLBVH_CL_DEVICE", "pocl")


@pytest.fixture(autouse=True)
def check_every_tree(monkeypatch):
    from invariants import check_tree

    from hlbvh_cl.scene import Scene

    rebuild, update_vertices = Scene.rebuild, Scene.update_vertices

    def checked_rebuild(self):
        rebuild(self)
        check_tree(self)

    def checked_update_vertices(self, geom_id, vertices):
        update_vertices(self, geom_id, vertices)
        check_tree(self)

    monkeypatch.setattr(Scene, "rebuild", checked_rebuild)
    monkeypatch.setattr(Scene, "update_vertices", checked_update_vertices)
