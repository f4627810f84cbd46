"""Device buffers recycled from one build to the next (one pool per Runtime).

A fresh buffer costs a CPU device its first-touch page faults, and the first
kernel that writes it pays them: a sizeable part of a large rebuild on PoCL.
So the build
stages take their buffers from the pool.  When a build ends, its scratch
buffers go back, and ``Scene.rebuild`` gives back the tree it replaces.

Buffers match by exact size, since a rebuild of the same geometry asks for the
same sizes.  Free buffers a build does not take stay, so that scenes rebuilt
in turn each find their own sizes again (two scenes rebuilt alternately
measured slower when each build dropped the other's buffers).
At the end of each build, what the pool keeps free is cut to KEEP_BUILDS times
the bytes of the largest build it has served, the buffers returned longest
ago first.  A Scene that goes away empties the pool (its memory is given back;
the other scenes' next rebuilds allocate afresh once).
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from contextlib import contextmanager

import pyopencl as cl

#: Free bytes kept, in builds of the largest size served: two scenes of that
#: size rebuilt in turn keep their own buffers.
KEEP_BUILDS = 2


class BufferPool:
    def __init__(self, allocate: Callable[[int], cl.Buffer]):
        self._allocate = allocate  # nbytes -> a fresh READ_WRITE buffer (Runtime.allocate)
        self._free: dict[int, list[cl.Buffer]] = {}  # by size, most recently returned last
        self._returned: dict[int, int] = {}          # id of a free buffer -> when it came back
        self._clock = 0
        self._budget = 0                             # KEEP_BUILDS x the largest build's bytes
        self._lock = threading.Lock()
        self._clear_pending = False  # clear() asked for while the lock was held (_locked)
        self._taken: list[cl.Buffer] | None = None  # during a build: every buffer it took
        self._kept: set[int] = set()                # ... and the ids of those it keeps

    def take(self, nbytes: int) -> cl.Buffer:
        """A READ_WRITE buffer of max(4, nbytes) bytes, recycled when one is free."""
        nbytes = max(4, int(nbytes))
        with self._locked():
            free = self._free.get(nbytes)
            buffer = free.pop() if free else None
            if buffer is not None:
                self._returned.pop(id(buffer), None)
        if buffer is None:
            buffer = self._allocate(nbytes)
        if self._taken is not None:
            self._taken.append(buffer)
        return buffer

    def take_spare(self, spare: list[cl.Buffer], nbytes: int) -> cl.Buffer:
        """A buffer of at least nbytes: the smallest of ``spare`` that holds
        them (removed from the list), else take(nbytes).  ``spare`` lists
        buffers of the current build that nothing enqueued later reads as
        what they held: the stages that size their buffers for the most
        they can need reuse the earlier stages' dead scratch, which keeps a
        build's peak memory down (issue 57).  The queue runs in order, so
        the new use starts after the old one ended."""
        fitting = [b for b in spare if b.size >= nbytes]
        if not fitting:
            return self.take(nbytes)
        chosen = min(fitting, key=lambda b: b.size)
        spare[:] = [b for b in spare if b != chosen]  # never handed out twice
        return chosen

    def give(self, *buffers: cl.Buffer | None) -> None:
        """Hand buffers back; the caller must not use them again."""
        with self._locked():
            self._clock += 1
            for buffer in buffers:
                if buffer is not None and id(buffer) not in self._returned:  # not twice
                    self._free.setdefault(buffer.size, []).append(buffer)
                    self._returned[id(buffer)] = self._clock

    def keep(self, *buffers: cl.Buffer) -> None:
        """Mark buffers taken in the current build as its results: they stay
        out of the pool when the build ends.  (Outside a build: nothing to do,
        as nothing taken comes back on its own.)"""
        if self._taken is not None:
            self._kept.update(id(b) for b in buffers)

    @contextmanager
    def build(self, keep_scratch: bool = True):
        """Scope of one build: whatever it takes and does not keep comes back
        at the end, even on an error; or, without ``keep_scratch``, is
        let go (a compact Scene's builds: it holds no more memory than its
        tree between them).  Nested scopes join the outermost."""
        if self._taken is not None:
            yield self
            return
        self._taken, self._kept = [], set()
        try:
            yield self
        finally:
            scratch = [b for b in self._taken if id(b) not in self._kept]
            if keep_scratch:
                self._budget = max(self._budget, KEEP_BUILDS * sum(b.size for b in self._taken))
            self._taken, self._kept = None, set()
            if keep_scratch:  # else dropped, as clear() drops them: freed when unreferenced
                self.give(*scratch)
                self._evict()

    def _evict(self) -> None:
        """Drop the buffers returned longest ago until the free bytes fit the
        budget."""
        with self._locked():
            excess = self.free_bytes - self._budget
            if excess <= 0:
                return
            free = sorted((b for buffers in self._free.values() for b in buffers),
                          key=lambda b: self._returned[id(b)])
            while excess > 0:
                dropped = free.pop(0)
                del self._returned[id(dropped)]
                excess -= dropped.size
            self._free = {}
            for buffer in free:
                self._free.setdefault(buffer.size, []).append(buffer)

    def clear(self) -> None:
        """Drop every free buffer (a Scene that goes away calls this, so that
        its last build's scratch does not outlive it).

        It never waits for the lock: a Scene's finalizer calls it, in any
        thread, and the garbage collector may run that finalizer inside a
        locked section of this very pool, in the same thread, where waiting
        would deadlock.  Where the lock is held, the holder drops the buffers
        as it leaves its section (_locked)."""
        self._clear_pending = True
        if self._lock.acquire(blocking=False):
            try:
                self._drop_pending()
            finally:
                self._lock.release()

    @contextmanager
    def _locked(self):
        """The lock, for a section that applies a clear() asked for meanwhile
        before it lets go."""
        with self._lock:
            try:
                yield
            finally:
                self._drop_pending()

    def _drop_pending(self) -> None:
        if self._clear_pending:  # (lock held)
            self._clear_pending = False
            self._free, self._returned, self._budget = {}, {}, 0

    @property
    def free_bytes(self) -> int:
        return sum(size * len(buffers) for size, buffers in self._free.items())
