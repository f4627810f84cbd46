"""Ctrl-C: a long render or query raises KeyboardInterrupt within a second,
and the process can trace again at once (kernels/queue state drained)."""
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent

CHILD = r"""
import sys, time
import numpy as np
import hlbvh_cl
mesh = hlbvh_cl.Mesh.load(sys.argv[1])
scene = hlbvh_cl.Scene([mesh])
renderer = hlbvh_cl.Renderer(scene)
lo, hi = scene._tree.bounds_lo, scene._tree.bounds_hi
camera = hlbvh_cl.Camera((lo + hi) / 2 + (hi - lo) * [0.3, 0.5, 1.6], (lo + hi) / 2)
rng = np.random.default_rng(0)
count = 8_000_000
origins = ((lo + hi) / 2 + rng.uniform(-0.5, 0.5, (count, 3)) * (hi - lo)).astype(np.float32)
directions = rng.normal(size=(count, 3)).astype(np.float32)
small = renderer.render(camera, 32, 24)  # compiles every kernel first
reference = scene.intersect(origins[:1000], directions[:1000])
one_job = {
    "render": lambda: renderer.render(camera, 2048, 1536, shading="ao", ao_samples=64, spp=4),
    "intersect": lambda: scene.intersect(origins, directions),
}[sys.argv[2]]
print("ready", flush=True)
try:
    deadline = time.monotonic() + 120  # one job may end before SIGINT on a fast device
    while time.monotonic() < deadline:
        one_job()
    print("finished", flush=True)
except KeyboardInterrupt:
    interrupted = time.monotonic()
    print("interrupted", flush=True)
    started = time.monotonic()
    again = renderer.render(camera, 32, 24)
    hits = scene.intersect(origins[:1000], directions[:1000])
    assert np.array_equal(again, small) and np.array_equal(hits.t, reference.t)
    print(f"again {time.monotonic() - started:.3f}", flush=True)
"""


@pytest.mark.parametrize("job", ["render", "intersect"])
def test_ctrl_c_stops_a_long_job_within_a_second(job):
    mesh = HERE.parent / "scenes" / "meshes" / "bunny.ply"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(mesh), job],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             cwd=HERE.parent)
    try:
        assert child.stdout.readline().strip() == "ready", child.stderr.read()
        time.sleep(1.5)  # well into the job
        sent = time.monotonic()
        child.send_signal(signal.SIGINT)
        line = child.stdout.readline().strip()
        waited = time.monotonic() - sent
        assert line == "interrupted", (line, child.stderr.read()[-3000:])
        assert waited < 2.0, f"KeyboardInterrupt came {waited:.2f} s after SIGINT"
        again = child.stdout.readline().strip()
        assert again.startswith("again"), (again, child.stderr.read()[-3000:])
        assert float(again.split()[1]) < 2.0, again  # no stall on work left queued
        assert child.wait(timeout=30) == 0
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
