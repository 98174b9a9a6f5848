"""Executors: where the episodes of an evaluation or a sweep run.

Each executor maps a picklable function over tasks and yields an :class:`Outcome` per task as
it finishes (completion order); a task that raises yields its traceback instead of a value.

- :class:`InlineExecutor`: in this process, one task after another.
- :class:`LocalExecutor`: a pool of ``workers`` spawned processes (default: every core this
  process may use), each with one BLAS thread (``OPENBLAS/OMP/MKL_NUM_THREADS=1`` are in the
  environment the workers start with, before numpy loads).
- :class:`RayExecutor`: Ray tasks (one CPU each, one BLAS thread) on a cluster (``"auto"``
  or an address) or on a local Ray instance (``"local"``); needs the ``cluster`` extra, and
  every node needs the same afvsgp-gym installed (records carry the code version each worker
  ran).

Episodes are deterministic given their spec, so every executor gives the same records (up to
the timing columns) in whatever order they finish.
"""

from __future__ import annotations

import contextlib
import os
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

__all__ = [
    "ONE_BLAS_THREAD",
    "InlineExecutor",
    "LocalExecutor",
    "Outcome",
    "RayExecutor",
    "available_cpus",
    "make_executor",
    "one_blas_thread",
    "require_ray",
]

#: Environment of every worker: one BLAS thread each (episodes are small, cores are few).
ONE_BLAS_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@dataclass
class Outcome:
    """The result of task ``index``: its ``value``, or ``error`` (a formatted traceback) and
    the ``exception`` itself (as raised in the worker, where the executor can carry it)."""

    index: int
    value: Any = None
    error: str | None = None
    exception: BaseException | None = None


def available_cpus() -> int:
    """Cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _positive(name: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{name} must be a positive integer, got {v!r}")
    return v


def _format(exc: BaseException) -> str:
    return "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)).rstrip()


class InlineExecutor:
    """Runs the tasks in this process, in order."""

    workers = 1

    def map_unordered(self, fn: Callable, tasks: Iterable) -> Iterator[Outcome]:
        for i, task in enumerate(tasks):
            try:
                value = fn(task)
            except Exception as exc:
                yield Outcome(i, error=_format(exc), exception=exc)
            else:
                yield Outcome(i, value)

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextlib.contextmanager
def _environ(values: dict[str, str]):
    """Set environment variables for processes started inside the block, then restore."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def one_blas_thread():
    """Context manager: processes started inside it run one BLAS thread each
    (:data:`ONE_BLAS_THREAD`; on a few cores, several processes each with a BLAS thread pool
    slow each other down several-fold on these small arrays)."""
    return _environ(ONE_BLAS_THREAD)


class LocalExecutor:
    """A pool of ``workers`` spawned worker processes on this machine (one BLAS thread each).

    The workers are started on the first task and reused until :meth:`close`; stopping the
    iteration early (an interrupt) cancels the pending tasks and terminates the workers.
    """

    def __init__(self, workers: int | None = None) -> None:
        self.workers = available_cpus() if workers is None else _positive("workers", workers)
        self._pool = None

    def _get_pool(self, n_tasks: int):
        if self._pool is None:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(max_workers=min(self.workers, max(n_tasks, 1)),
                                             mp_context=mp.get_context("spawn"))
        return self._pool

    def map_unordered(self, fn: Callable, tasks: Iterable) -> Iterator[Outcome]:
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        tasks = list(tasks)
        if not tasks:
            return
        pool = self._get_pool(len(tasks))
        with one_blas_thread():  # workers are spawned on submit and inherit it
            pending = {pool.submit(fn, t): i for i, t in enumerate(tasks)}
        try:
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = pending.pop(fut)
                    exc = fut.exception()
                    if isinstance(exc, BrokenProcessPool):
                        raise RuntimeError(
                            "a worker process died (killed, out of memory or crashed); the "
                            f"pool is unusable: {exc}") from exc
                    if exc is None:
                        yield Outcome(i, fut.result())
                    else:
                        yield Outcome(i, error=_format(exc), exception=exc)
        finally:
            if pending:  # interrupted or abandoned: stop now rather than finish the queue
                self._terminate()

    def _terminate(self) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        procs = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            p.terminate()
        for p in procs:
            p.join(timeout=5)

    def close(self) -> None:
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def require_ray():
    """Import ray, or raise ImportError naming the ``cluster`` extra."""
    try:
        import ray
    except ImportError:
        raise ImportError(
            "the Ray executor needs ray: pip install 'afvsgp-gym[cluster]'") from None
    return ray


def _call(fn: Callable, task: Any) -> Any:
    return fn(task)


class RayExecutor:
    """Ray tasks, one CPU each, with one BLAS thread.

    ``address``: ``"auto"`` (the cluster this machine belongs to, e.g. after ``ray start``),
    ``"ray://host:port"`` or ``"host:port"``, or ``"local"`` (start a private Ray instance with
    ``num_cpus`` CPUs, default all). When Ray is already initialised in this process its
    connection is used as is (and left open on :meth:`close`).
    """

    def __init__(self, address: str = "auto", *, num_cpus: int | None = None) -> None:
        ray = require_ray()
        self._ray = ray
        self._owns = not ray.is_initialized()
        if self._owns:
            if address == "local":
                ray.init(num_cpus=num_cpus, include_dashboard=False)
            else:
                ray.init(address=address)
        self.workers = max(1, int(ray.cluster_resources().get("CPU", 1)))

    def map_unordered(self, fn: Callable, tasks: Iterable) -> Iterator[Outcome]:
        ray = self._ray
        remote = ray.remote(num_cpus=1)(_call).options(
            runtime_env={"env_vars": dict(ONE_BLAS_THREAD)})
        fn_ref = ray.put(fn)
        pending = {remote.remote(fn_ref, t): i for i, t in enumerate(tasks)}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    i = pending.pop(ref)
                    try:
                        value = ray.get(ref)
                    except Exception as exc:  # RayTaskError carries the worker's traceback
                        cause = getattr(exc, "cause", None)
                        yield Outcome(i, error=str(exc),
                                      exception=cause if isinstance(cause, Exception) else exc)
                    else:
                        yield Outcome(i, value)
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self._owns and self._ray.is_initialized():
            self._ray.shutdown()
        self._owns = False

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def make_executor(workers: int | None = 1, ray: str | None = None, *,
                  inline_single: bool = True):
    """The executor for ``--workers``/``--ray``: Ray when ``ray`` is an address, else a local
    pool of ``workers`` processes (None: every core), or this process when ``workers == 1``
    and ``inline_single``."""
    if ray:
        return RayExecutor(ray, num_cpus=workers if ray == "local" else None)
    if workers == 1 and inline_single:
        return InlineExecutor()
    return LocalExecutor(workers)
