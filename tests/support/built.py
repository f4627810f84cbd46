"""A built scene's tree and runtime for tests, read through Scene.borrow(),
the scene's one documented way in (it raises RuntimeError where the scene
has no tree: a test that expects none asserts that instead)."""


def tree(scene):
    """The tree ``scene``'s queries walk now: a Tree, or an instanced
    scene's InstancedTree."""
    with scene.borrow() as built:
        return built.tree


def runtime(scene):
    """The hlbvh_cl.device.runtime.Runtime of ``scene``'s device."""
    with scene.borrow() as built:
        return built.runtime
