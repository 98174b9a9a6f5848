"""The results file of a sweep: one JSON record per finished episode, appended as it finishes.

Each line is written whole, flushed and fsynced before the next episode is counted, so a killed
sweep loses at most the episodes still running. On reopening, a torn last line (the process
was killed while writing it) is dropped, unless it is a complete record that only lacks its
newline; any other unreadable line is an error naming its line number, since silently dropping
it would lose a finished episode. One sweep writes a file at a time (an exclusive ``flock``).
"""

from __future__ import annotations

import gzip
import json
import os
import zlib
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from afvsgp_gym.evaluation import jsonable

__all__ = ["ResultsLog", "read_records"]


def _parse(path: Path, data: bytes) -> tuple[list[dict], int]:
    """Records of ``data`` and the byte length of its valid part (torn tail excluded)."""
    records: list[dict] = []
    lines = data.split(b"\n")
    tail = lines.pop()  # b"" when data ends with a newline
    offset = 0
    for number, line in enumerate(lines, start=1):
        offset += len(line) + 1
        if not line.strip():
            continue
        records.append(_record(path, number, line))
    keep = offset
    if tail.strip():
        try:
            rec = _record(path, len(lines) + 1, tail)
        except ValueError:
            pass  # a torn last line: the episode was not finished
        else:
            records.append(rec)
            keep += len(tail)
    return records, keep


def _record(path: Path, number: int, line: bytes) -> dict:
    try:
        rec = json.loads(line)
    except ValueError as exc:
        raise ValueError(f"{path}: line {number} is not a JSON record ({exc}); the file was "
                         "changed by something else than a sweep: fix or remove that line"
                         ) from None
    if not isinstance(rec, dict) or "key" not in rec:
        raise ValueError(f"{path}: line {number} is not an episode record (no 'key')")
    return rec


def read_records(path: str | os.PathLike) -> list[dict]:
    """Every finished episode record of a results file, plain or gzip-compressed (as archived
    in ``benchmarks/results``); a torn last line is ignored."""
    path = Path(path)
    try:
        data = path.read_bytes()
        if data[:2] == b"\x1f\x8b":  # the gzip magic number
            data = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as exc:
        raise ValueError(f"cannot read results {str(path)!r}: {exc}") from None
    return _parse(path, data)[0]


class ResultsLog:
    """Append-only JSON-lines results file, opened for one sweep (a context manager).

    ``records`` are the finished episodes found on opening (plus those appended since);
    ``keys`` their episode keys.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.records: list[dict] = []
        self.keys: set[str] = set()
        self._fh = None

    def __enter__(self) -> ResultsLog:
        import fcntl

        self.path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(self.path, "a+b")  # noqa: SIM115 - closed in __exit__
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.close()
            raise RuntimeError(f"{self.path} is being written by another sweep") from None
        try:
            fh.seek(0)
            data = fh.read()
            self.records, keep = _parse(self.path, data)
            if keep < len(data):  # drop the torn tail before appending after it
                fh.truncate(keep)
            elif data and not data.endswith(b"\n"):  # a complete last record without newline
                fh.write(b"\n")
            fh.flush()
            os.fsync(fh.fileno())
        except BaseException:
            fh.close()
            raise
        self.keys = {r["key"] for r in self.records}
        self._fh = fh
        return self

    def append(self, record: Mapping[str, Any]) -> None:
        """Write one record as a line, flushed and fsynced."""
        if self._fh is None:
            raise RuntimeError("ResultsLog.append outside its with-block")
        line = json.dumps(jsonable(record), allow_nan=False, separators=(",", ":")) + "\n"
        self._fh.write(line.encode())
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self.records.append(dict(record))
        self.keys.add(record["key"])

    def __iter__(self) -> Iterator[dict]:
        return iter(self.records)

    def __exit__(self, *exc) -> None:
        if self._fh is not None:
            self._fh.close()  # releases the lock
            self._fh = None
