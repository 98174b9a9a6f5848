"""A progress bar over episodes with the running count of episodes with cost (stderr)."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any

__all__ = ["EpisodeProgress"]


class EpisodeProgress:
    """tqdm bar over ``total`` episodes, ``done`` of them already finished (``with_cost`` of
    those with cost); :meth:`update` counts one finished episode record. Disabled: no output."""

    def __init__(self, total: int, *, done: int = 0, with_cost: int = 0, desc: str = "episodes",
                 enabled: bool = True) -> None:
        self.with_cost = int(with_cost)
        self.failed = 0
        self._bar = None
        if enabled:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total, initial=done, unit="ep", desc=desc, file=sys.stderr,
                             dynamic_ncols=True, mininterval=0.5, smoothing=0.05)
            self._postfix()

    def _postfix(self) -> None:
        text = f"with cost {self.with_cost}"
        if self.failed:
            text += f", failed {self.failed}"
        self._bar.set_postfix_str(text, refresh=False)

    def update(self, record: Mapping[str, Any] | None) -> None:
        """One more episode: its record, or None when it failed."""
        if record is None:
            self.failed += 1
        elif int(record["cost_steps"]) > 0:
            self.with_cost += 1
        if self._bar is not None:
            self._postfix()
            self._bar.update(1)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
