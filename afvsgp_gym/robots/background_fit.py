"""The learners' warm-up fit in a process of its own, so that the 1 kHz loop goes on.

Algorithm 1 fits the learners once, on the warm-up samples (line 3: the hyperparameters and
the first inducing sets). For the bridge's barriers that takes about half a second, hundreds
of ticks of a 1 kHz loop; a robot answers 20 lost commands in 100 with
``communication_constraints_violation``. :class:`BackgroundFit` runs the fit in a worker (a
fresh interpreter, ``python -m`` this module), started and ready before the loop:

1. after a write, once the warm-up samples are in (``SafetyController.warmup_complete``),
   :meth:`BackgroundFit.submit` writes them into a shared memory block (1.6 MB for 49
   barriers, mapped and touched before the loop) and sends the worker a few kilobytes: the
   unfitted bank, pickled;
2. the worker fits the bank (:func:`~afvsgp_gym.cbf.controller.fit_bank`, the code
   ``SafetyController.fit`` runs), pickles it with its arrays out of band into a new shared
   memory block, and sends their places;
3. after a later write, :meth:`BackgroundFit.poll` maps that block and unpickles the bank on
   it without a copy (the arrays, 20 MB with their windows, are the block's pages), and the
   bridge installs it (``SafetyController.install_fitted``).

Meanwhile the filter runs as in the warm-up, and the samples of those ticks are not learned.
The fitted bank is the one ``SafetyController.fit`` makes of the same samples (tested: with
the answer awaited, the run is the fit-in-the-loop run bit for bit). The worker runs at
normal priority: it must not take a core from a loop at ``SCHED_FIFO``.
"""

from __future__ import annotations

import os
import pickle
import secrets
import subprocess
import sys
from multiprocessing import resource_tracker
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

__all__ = ["BackgroundFit"]

_READY = "ready"


class _Pipes:
    """The two one-way connections to the worker as one (``poll``, ``recv``, ``send``)."""

    def __init__(self, incoming: Connection, outgoing: Connection):
        self.incoming, self.outgoing = incoming, outgoing
        self.poll, self.recv, self.send = incoming.poll, incoming.recv, outgoing.send

    def close(self) -> None:
        self.incoming.close()
        self.outgoing.close()


class _Block(SharedMemory):
    """A shared memory block whose arrays may outlive this object: the mapping goes when
    the last of them does (``SharedMemory`` would refuse to close under them)."""

    def __del__(self) -> None:
        try:
            self.close()
        except (BufferError, OSError):
            pass


def _untracked(shm: SharedMemory) -> SharedMemory:
    """``shm`` left out of this process's resource tracker (the bridge unlinks the blocks;
    the tracker would try again at exit)."""
    try:
        resource_tracker.unregister(shm._name, "shared_memory")  # noqa: SLF001 (3.13: track=)
    except (AttributeError, KeyError, ValueError):
        pass
    return shm


def _to_shared(arrays: list, name: str) -> tuple[SharedMemory, list[tuple[int, int]]]:
    """A shared memory block ``name`` holding the bytes of ``arrays`` (buffers), and each
    one's ``(offset, size)``."""
    views = [memoryview(a).cast("B") for a in arrays]
    places, offset = [], 0
    for v in views:
        places.append((offset, v.nbytes))
        offset += v.nbytes
    shm = SharedMemory(name=name, create=True, size=max(offset, 1))
    for v, (o, n) in zip(views, places, strict=True):
        shm.buf[o:o + n] = v
    return shm, places


def _worker(conn: Any) -> None:
    """The fitting process: normal priority, then one job per message (``conn``) until
    None."""
    if hasattr(os, "sched_setscheduler"):  # do not inherit the loop's SCHED_FIFO
        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except OSError:
            pass
    from afvsgp_gym.cbf.controller import fit_bank, split_samples

    conn.send(_READY)
    while True:
        job = conn.recv()
        if job is None:
            break
        bank_bytes, name, places, shapes, action_dim, learn, result = job
        try:
            shm = _untracked(SharedMemory(name=name))
            try:
                xi, u, z = (np.ndarray(shape, np.float64, shm.buf, offset=o).copy()
                            for shape, (o, _) in zip(shapes, places, strict=True))
            finally:
                shm.close()
            bank = pickle.loads(bank_bytes)
            fit_bank(bank, split_samples(xi, u, z), action_dim, learn)
            buffers: list = []
            meta = pickle.dumps(bank, protocol=5, buffer_callback=buffers.append)
            out, out_places = _to_shared([b.raw() for b in buffers], result)
            _untracked(out).close()  # the block stays until the bridge unlinks it
            conn.send(("ok", meta, out_places))
        except Exception as exc:  # reported to the bridge, which goes on unfitted
            conn.send(("error", f"{type(exc).__name__}: {exc}", None))


class BackgroundFit:
    """The warm-up fit of a :class:`~afvsgp_gym.cbf.controller.SafetyController`'s learners in
    a worker process (module docstring). :meth:`start` before the loop (it waits until
    the worker has imported the package: about a second) with the samples' ``shapes`` (their
    block is then mapped and touched before the loop, not in it), :meth:`submit` and
    :meth:`poll` after writes, :meth:`close` after the loop. ``error`` holds a failed fit's
    message (the controller stays unfitted: the filter goes on as in the warm-up)."""

    def __init__(self) -> None:
        self._conn: _Pipes | None = None
        self._process: subprocess.Popen | None = None
        self._samples: SharedMemory | None = None
        self._places: list[tuple[int, int]] = []
        self._shapes: tuple | None = None
        #: the blocks the fitted banks' arrays live in (unlinked; mapped while they are used)
        self.blocks: list[SharedMemory] = []
        self.pending = False
        self._result = ""  # the name of the fitted bank's block (made by the worker)
        self.error: str | None = None

    def start(self, shapes: tuple | None = None, timeout: float = 60.0) -> BackgroundFit:
        """Start the worker; ``shapes``: those of the samples ``xi`` (K, N, b), ``u`` (N, m),
        ``z`` (K, N) (``SafetyController.warmup_samples``), for the block they go to."""
        # a fresh interpreter (``python -m`` this module), not multiprocessing's spawn, which
        # would import the user's main script again in the worker
        from_parent, to_child = os.pipe()  # (read end, write end)
        from_child, to_parent = os.pipe()
        self._process = subprocess.Popen(
            [sys.executable, "-m", __name__, str(from_parent), str(to_parent)],
            pass_fds=(from_parent, to_parent), close_fds=True)
        os.close(from_parent)
        os.close(to_parent)
        self._conn = _Pipes(Connection(from_child, writable=False),
                            Connection(to_child, readable=False))
        if shapes is not None:
            self._reserve(tuple(tuple(int(n) for n in shape) for shape in shapes))
        if not self._conn.poll(timeout) or self._conn.recv() != _READY:
            self.close()
            raise RuntimeError(f"the fitting process did not start within {timeout} s")
        return self

    def _reserve(self, shapes: tuple) -> None:
        """The samples' block for ``shapes``, its pages touched."""
        self._release_samples()
        sizes = [8 * int(np.prod(shape)) for shape in shapes]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int).tolist()
        self._samples = SharedMemory(create=True, size=max(sum(sizes), 1))
        np.ndarray(self._samples.size, np.uint8, self._samples.buf).fill(0)
        self._places = list(zip(offsets, sizes, strict=True))
        self._shapes = shapes

    def _sample_views(self) -> list[np.ndarray]:
        return [np.ndarray(shape, np.float64, self._samples.buf, offset=o)
                for shape, (o, _) in zip(self._shapes, self._places, strict=True)]

    def submit(self, controller: Any) -> None:
        """Send ``controller``'s warm-up samples and unfitted bank to the worker."""
        if self._conn is None:
            raise RuntimeError("BackgroundFit.submit before start()")
        if self.pending:
            raise RuntimeError("a fit is already running")
        shapes = controller.warmup_shapes()
        if shapes != self._shapes:  # not reserved (or not these): a block now
            self._reserve(shapes)
        views = self._sample_views()
        controller.warmup_samples(out=views)
        self._result = f"afvsgp_fit_{os.getpid()}_{secrets.token_hex(6)}"
        self._conn.send((pickle.dumps(controller.bank), self._samples.name, self._places,
                         self._shapes, controller.action_dim,
                         controller.config.learn_hyperparameters, self._result))
        self.pending = True

    def poll(self, wait: float = 0.0) -> Any | None:
        """The fitted bank once the worker sent it (waiting up to ``wait`` s), else None."""
        if not self.pending or not self._conn.poll(wait):
            return None
        status, meta, places = self._conn.recv()
        self.pending = False
        if status != "ok":
            self.error = meta
            return None
        block = _Block(name=self._result)
        block.unlink()  # the name goes; the mapping stays while the bank's arrays use it
        self.blocks.append(block)
        return pickle.loads(meta, buffers=[block.buf[o:o + n] for o, n in places])

    def close(self) -> None:
        """Stop the worker (a fit still running is abandoned) and free the samples' block."""
        if self.pending and self._process is not None:
            self._process.kill()  # mid-fit: its result is not wanted, nor its block
        if self._conn is not None:
            try:
                self._conn.send(None)
            except (OSError, ValueError):
                pass
        if self._process is not None:
            try:
                self._process.wait(5.0)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait(1.0)
        if self._conn is not None:
            self._conn.close()
        self._conn = self._process = None
        if self.pending:  # the abandoned fit's block, if it was made
            self.pending = False
            try:
                SharedMemory(name=self._result).unlink()
            except FileNotFoundError:
                pass
        self._release_samples()

    def _release_samples(self) -> None:
        if self._samples is not None:
            self._samples.close()
            self._samples.unlink()
            self._samples, self._shapes = None, None

    def __enter__(self) -> BackgroundFit:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


if __name__ == "__main__":  # the worker: python -m afvsgp_gym.robots.background_fit IN OUT
    _worker(_Pipes(Connection(int(sys.argv[1]), writable=False),
                   Connection(int(sys.argv[2]), readable=False)))
