"""Run a sweep: the episodes not yet in the results file, through an executor, appended as
they finish (see :mod:`afvsgp_gym.sweep.results`), with a progress bar over episodes."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from afvsgp_gym.evaluation import EpisodeSpec, code_version, run_spec
from afvsgp_gym.progress import EpisodeProgress
from afvsgp_gym.sweep.results import ResultsLog

__all__ = ["SweepResult", "run_sweep"]


@dataclass
class SweepResult:
    """What a sweep call did: ``records`` of every episode of the grid found or run,
    ``skipped`` (already in the file), ``ran``, ``failed`` ``(spec, traceback)`` pairs."""

    records: list[dict] = field(default_factory=list)
    skipped: int = 0
    ran: int = 0
    failed: list[tuple[EpisodeSpec, str]] = field(default_factory=list)


def _task(spec: EpisodeSpec) -> dict:
    return run_spec(spec)[0]


class _TerminateAsInterrupt:
    """Within the block, SIGTERM raises KeyboardInterrupt (so workers are stopped cleanly)."""

    def __enter__(self):
        self._old = None
        if hasattr(signal, "SIGTERM"):
            try:
                self._old = signal.signal(signal.SIGTERM, self._raise)
            except ValueError:  # not the main thread: leave signals alone
                self._old = None
        return self

    @staticmethod
    def _raise(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGTERM, self._old)


def run_sweep(
    episodes: Sequence[tuple[str, EpisodeSpec]],
    results_path: str | os.PathLike,
    executor: Any,
    *,
    progress: bool = True,
    limit: int | None = None,
    log: Callable[[str], None] | None = None,
) -> SweepResult:
    """Run the ``(block, spec)`` episodes missing from ``results_path`` on ``executor``.

    Finished episodes (same :meth:`EpisodeSpec.key`) are skipped; ``limit`` runs at most that
    many of the others (the first in order: a sweep run in slices). Each new record gets its
    ``block`` and is appended as soon as it arrives. A failing episode is reported through
    ``log`` and left out of the file (a re-run retries it). SIGTERM and Ctrl-C stop the
    workers and keep every finished record; re-running the same command resumes.
    """
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    out = SweepResult()
    wanted = {spec.key(): (block, spec) for block, spec in episodes}
    with ResultsLog(results_path) as results, _TerminateAsInterrupt():
        done = {r["key"]: r for r in results.records if r["key"] in wanted}
        out.skipped = len(done)
        todo = [(b, s) for k, (b, s) in wanted.items() if k not in done]
        if done:
            log(f"{results_path}: {len(done)} of {len(wanted)} episodes already finished, "
                f"{len(todo)} to run")
        if limit is not None:
            todo = todo[:limit]
        with_cost = sum(int(r["cost_steps"]) > 0 for r in done.values())
        with EpisodeProgress(len(done) + len(todo), done=len(done), with_cost=with_cost,
                             desc="sweep", enabled=progress) as bar:
            outcomes = executor.map_unordered(_task, [s for _, s in todo])
            with contextlib.closing(outcomes):  # closing stops the workers on an interrupt
                for res in outcomes:
                    block, spec = todo[res.index]
                    if res.error is not None:
                        out.failed.append((spec, res.error))
                        log(f"episode failed ({block}, seed {spec.seed}, {spec.config()}):\n"
                            f"{res.error}")
                        bar.update(None)
                        continue
                    record = {"block": block, **res.value}
                    results.append(record)
                    done[record["key"]] = record
                    out.ran += 1
                    bar.update(record)
        out.records = [done[k] for k in wanted if k in done]
    versions = {r.get("code_version") for r in out.records}
    if len(versions) > 1:
        log(f"note: the records come from {len(versions)} code versions "
            f"({', '.join(sorted(map(str, versions)))}); this process runs {code_version()}")
    return out
