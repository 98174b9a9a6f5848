"""What determines one episode: :class:`EpisodeSpec`, its config and its identity."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from afvsgp_gym.evaluation.io import jsonable

__all__ = ["UNFILTERED", "EpisodeSpec"]

#: The name of "no filter" where a learner name is expected (``--compare``, sweep configs).
UNFILTERED = "unfiltered"


@dataclass(frozen=True)
class EpisodeSpec:
    """Everything that determines one episode.

    ``learner=None`` runs the bare env (no filter). ``filter_kwargs`` go to
    :class:`afvsgp_gym.wrappers.SafetyFilter`; unless they set ``seed``, the filter is seeded
    with the episode seed. ``max_steps`` caps the episode below the env's time limit.
    """

    env_id: str
    seed: int
    learner: str | None = "afvsgp"
    agent: str = "nominal"
    env_kwargs: Mapping[str, Any] = field(default_factory=dict)
    filter_kwargs: Mapping[str, Any] = field(default_factory=dict)
    max_steps: int | None = None

    def config(self) -> dict[str, Any]:
        """The spec without its seed, as plain JSON data (kwargs with sorted keys)."""
        return {
            "env_id": self.env_id,
            "env_kwargs": jsonable(dict(sorted(self.env_kwargs.items()))),
            "learner": self.learner,
            "filter_kwargs": jsonable(dict(sorted(self.filter_kwargs.items()))),
            "agent": self.agent,
            "max_steps": self.max_steps,
        }

    def key(self) -> str:
        """SHA-256 of the canonical JSON of the config and the seed: the episode's identity
        (an object JSON cannot hold, e.g. a callable ``backup``, enters by its ``repr``)."""
        text = json.dumps({**self.config(), "seed": int(self.seed)}, sort_keys=True,
                          separators=(",", ":"), allow_nan=False, default=repr)
        return hashlib.sha256(text.encode()).hexdigest()

    @property
    def learner_name(self) -> str:
        return UNFILTERED if self.learner is None else str(self.learner)
