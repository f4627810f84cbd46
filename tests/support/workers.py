"""What test_processes.py's worker processes run: importable by name, as
spawn's children need (they unpickle the functions by reference)."""
import numpy as np

#: The rays each worker traces: straight down onto the grid of shapes.grid_mesh(4).
ORIGINS = np.stack(np.meshgrid(np.linspace(0.3, 3.7, 6), np.linspace(0.3, 3.7, 6)),
                   axis=-1).reshape(-1, 2)
ORIGINS = np.hstack([ORIGINS, np.full((len(ORIGINS), 1), 2.0)])
DOWN = np.array([0.0, 0.0, -1.0])

_scene = None


def inherit(scene) -> None:
    """Keeps ``scene`` where a forked child finds it (a module global, as a
    script's would be)."""
    global _scene
    _scene = scene


def trace_inherited(row: int) -> float:
    """In a forked child: ray ``row`` against the scene the parent made."""
    return float(_scene.intersect(ORIGINS[row], DOWN[None]).t[0])


def trace(scene, rows) -> np.ndarray:
    """In any process: the rays ``rows`` against ``scene`` (pickled there)."""
    return scene.intersect(ORIGINS[rows], DOWN).t


class Dataset:
    """A map-style dataset as PyTorch's DataLoader takes one: item i is ray
    i's depth, traced in whichever worker asks for it."""

    def __init__(self, scene):
        self.scene = scene

    def __len__(self) -> int:
        return len(ORIGINS)

    def __getitem__(self, i: int) -> np.float32:
        return np.float32(self.scene.intersect(ORIGINS[i], DOWN[None]).t[0])


def loader_worker(dataset, indices, results) -> None:
    """A DataLoader worker's loop, as torch.utils.data's _worker_loop runs
    it: take an index, fetch the item, send it back, and send an exception
    back too (wrapped, where torch wraps it in an ExceptionWrapper)."""
    while True:
        i = indices.get()
        if i is None:
            return
        try:
            results.put((i, dataset[i], None))
        except Exception as error:  # the parent re-raises it, as DataLoader does
            results.put((i, None, (type(error).__name__, str(error))))
