"""Stable-Baselines3 agents trained with the safety filter in the loop.

Thin helpers in the spirit of SB3's ``Monitor``: :func:`train` builds
``make_vec_env(env_id, wrapper_class=SafetyFilter)``, trains PPO or SAC while a
:class:`CostCallback` accumulates ``info["cost"]`` per episode (SB3's ``info_keywords`` would only
see the last step), and saves a ``.zip``; :func:`load_policy` turns that zip back into an
``obs -> action`` callable for :func:`afvsgp_gym.evaluation.evaluate`.

Stable-Baselines3 is an optional extra: ``pip install afvsgp-gym[rl]``.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["ALGOS", "TrainResult", "load_policy", "require_sb3", "train"]

ALGOS = ("ppo", "sac")
_EXTRA_MSG = (
    "Stable-Baselines3 is not installed; it is an optional extra: pip install 'afvsgp-gym[rl]'"
)


def require_sb3() -> Any:
    """Import ``stable_baselines3``; an ``ImportError`` names the ``rl`` extra if absent."""
    try:
        import stable_baselines3
    except ImportError as exc:
        raise ImportError(_EXTRA_MSG) from exc
    return stable_baselines3


def _algo_class(algo: str) -> Any:
    sb3 = require_sb3()
    algo = algo.lower()
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {', '.join(ALGOS)}, got {algo!r}")
    return sb3.PPO if algo == "ppo" else sb3.SAC


def _cost_callback_class() -> type:
    from stable_baselines3.common.callbacks import BaseCallback

    class CostCallback(BaseCallback):
        """Sum ``info["cost"]`` per episode and per env; logs ``safety/episode_cost``."""

        def __init__(self, verbose: int = 0):
            super().__init__(verbose)
            self.episode_costs: list[float] = []
            self.episode_interventions: list[int] = []
            self._cost: np.ndarray | None = None
            self._interv: np.ndarray | None = None

        def _on_step(self) -> bool:
            infos = self.locals["infos"]
            dones = self.locals["dones"]
            if self._cost is None:
                self._cost = np.zeros(len(infos))
                self._interv = np.zeros(len(infos), dtype=int)
            for k, info in enumerate(infos):
                self._cost[k] += float(info.get("cost", 0.0))
                self._interv[k] += int(bool(info.get("filter_active", False)))
                if dones[k]:
                    self.episode_costs.append(float(self._cost[k]))
                    self.episode_interventions.append(int(self._interv[k]))
                    self.logger.record("safety/episode_cost", float(self._cost[k]))
                    self.logger.record("safety/episode_interventions", int(self._interv[k]))
                    self._cost[k] = 0.0
                    self._interv[k] = 0
            return True

    return CostCallback


@dataclass
class TrainResult:
    """Where the model went and the safety cost of every finished training episode."""

    path: Path
    episode_costs: list[float] = field(default_factory=list)
    episode_interventions: list[int] = field(default_factory=list)


def train(
    algo: str,
    env_id: str,
    *,
    learner: str | None = "afvsgp",
    timesteps: int = 10_000,
    path: str | os.PathLike = "agent.zip",
    seed: int = 0,
    n_envs: int = 1,
    env_kwargs: dict | None = None,
    filter_kwargs: dict | None = None,
    algo_kwargs: dict | None = None,
    verbose: int = 0,
) -> TrainResult:
    """Train ``algo`` ("ppo" | "sac") on ``env_id`` behind ``SafetyFilter(learner=...)``.

    ``learner=None`` trains on the bare environment (no filter). The model is saved to ``path``
    (a ``.zip``) and reloadable with :func:`load_policy`.
    """
    cls = _algo_class(algo)
    from stable_baselines3.common.env_util import make_vec_env

    import afvsgp_gym  # noqa: F401  (registers the ids)

    if timesteps < 1:
        raise ValueError(f"timesteps must be a positive integer, got {timesteps}")
    wrapper_class = wrapper_kwargs = None
    if learner is not None:
        from afvsgp_gym.wrappers import SafetyFilter

        wrapper_class = SafetyFilter
        wrapper_kwargs = {"learner": learner, **(filter_kwargs or {})}
    venv = make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs,
                        wrapper_class=wrapper_class, wrapper_kwargs=wrapper_kwargs)
    kwargs: dict[str, Any] = {"seed": seed, "verbose": verbose, "device": "cpu"}
    if algo.lower() == "ppo":
        # rollout length a multiple of the mini-batch (64) so no mini-batch is truncated
        kwargs["n_steps"] = max(64, min(2048, int(timesteps) // n_envs // 64 * 64))
        kwargs["batch_size"] = 64
    else:
        kwargs["learning_starts"] = min(100, int(timesteps) // 2)
    kwargs.update(algo_kwargs or {})
    model = cls("MlpPolicy", venv, **kwargs)
    callback = _cost_callback_class()(verbose=verbose)
    try:
        model.learn(total_timesteps=int(timesteps), callback=callback)
    finally:
        venv.close()
    path = Path(path)
    if path.suffix != ".zip":
        path = path.with_suffix(path.suffix + ".zip")
    model.save(path)
    return TrainResult(path, callback.episode_costs, callback.episode_interventions)


def _detect_algo(path: Path) -> str:
    """Read the algorithm from the zip's ``data`` entry (its algorithm-specific keys)."""
    try:
        with zipfile.ZipFile(path) as zf:
            data = json.loads(zf.read("data"))
    except (OSError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise ValueError(f"{str(path)!r} is not a Stable-Baselines3 model zip: {exc}") from None
    if "clip_range" in data:  # PPO-only hyperparameter
        return "ppo"
    if "target_entropy" in data:  # SAC-only hyperparameter
        return "sac"
    raise ValueError(f"cannot tell the algorithm of {str(path)!r}; supported: {', '.join(ALGOS)}")


def load_policy(path: str | os.PathLike, *, deterministic: bool = True, env: Any = None) -> Any:
    """Load a PPO/SAC zip saved by :func:`train` as an ``obs -> action`` callable.

    With ``env``, its observation and action spaces must match the model's (ValueError).
    """
    require_sb3()
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"agent zip {str(path)!r} does not exist")
    model = _algo_class(_detect_algo(path)).load(path, device="cpu")
    if env is not None:
        for kind in ("observation_space", "action_space"):
            want, got = getattr(model, kind).shape, getattr(env, kind).shape
            if want != got:
                raise ValueError(f"agent {str(path)!r} was trained with {kind} of shape {want}, "
                                 f"the env has {got}: train it on this env id")

    def policy(obs: np.ndarray) -> np.ndarray:
        action, _ = model.predict(obs, deterministic=deterministic)
        return np.asarray(action, dtype=np.float32)

    policy.model = model  # type: ignore[attr-defined]
    return policy
