"""Runtime.wait on a GPU first polls its events on the calling thread
(spin_seconds), then blocks on a thread of its own (which Ctrl-C can
interrupt: tests/test_interrupt.py).  Polling sees completion, gives up at
its deadline, and leaves every answer as it was."""
import time

import numpy as np
import pyopencl as cl

import hlbvh_cl
from hlbvh_cl.device.runtime import polled, runtime


def test_polling_sees_completion_and_gives_up_at_its_deadline(suite_device):
    rt = runtime(suite_device)
    queue = cl.CommandQueue(rt.context)  # its own: a gate left shut stalls no other test
    gate = cl.UserEvent(rt.context)
    buffer = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 16)
    fill = cl.enqueue_fill_buffer(queue, buffer, np.int32(7), 0, 16, wait_for=[gate])
    try:
        started = time.perf_counter()
        assert not polled([fill, gate], 0.05)  # the gate holds the fill back
        assert time.perf_counter() - started >= 0.05  # it polled until its deadline
    finally:
        gate.set_status(cl.command_execution_status.COMPLETE)
    assert polled([fill, gate], 30.0)
    out = np.zeros(4, np.int32)
    cl.enqueue_copy(queue, out, buffer)
    assert out.tolist() == [7] * 4


def test_a_polling_wait_gives_the_same_answers(suite_device, meshes, monkeypatch):
    scene = hlbvh_cl.Scene([meshes["bunny_small"]], device=suite_device)
    rng = np.random.default_rng(5)
    origins = rng.uniform(-0.2, 0.2, (3000, 3)).astype(np.float32)
    directions = rng.normal(size=(3000, 3)).astype(np.float32)
    want = scene.intersect(origins, directions)
    for spin in (0.0, 30.0):  # never, and (in effect) always by polling
        monkeypatch.setattr(runtime(suite_device), "spin_seconds", spin)
        got = scene.intersect(origins, directions)
        for name in ("t", "u", "v", "prim_id", "geom_id"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), name)
        assert (got.prim_id >= 0).any()
