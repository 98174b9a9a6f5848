"""Stable-Baselines3 agents trained with the safety filter in the loop.

:func:`train` builds ``make_vec_env(env_id, n_envs, vec_env_cls=SubprocVecEnv)`` (one process
per env when ``n_envs > 1``), each env wrapped by :func:`wrap_env` as::

    gym.make(env_id) -> Monitor -> SafetyFilter(learner) -> EpisodeSafetyStats -> ActionRepeat

(no ``SafetyFilter`` with ``learner=None``). The filter, and what its learners learned, persist
across the episodes of one env; every worker process has its own. The agent acts every
``action_repeat`` env steps (the env's ``action_repeat`` attribute by default, 10 steps = 40 ms
on the Franka reach task), the filter at every env step.

An :class:`EpisodeLogger` callback writes one CSV row per finished episode (return, success,
cost steps, interventions, backup and infeasible steps, ...; see
:data:`~afvsgp_gym.wrappers.episode_safety.EPISODE_SAFETY_FIELDS`) and records their means
and the cumulative cost in SB3's logger (``safety/*``, ``rollout/success_rate``), written as
CSV (and TensorBoard when installed) under ``log_dir``. The model zip records the env id,
the filter and the action repeat, so :func:`load_policy` acts like the training loop: it holds
each action for ``action_repeat`` calls.

Stable-Baselines3 is an optional extra: ``pip install afvsgp-gym[rl]``.
"""

from __future__ import annotations

import csv
import json
import os
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from afvsgp_gym.wrappers.episode_safety import EPISODE_SAFETY_FIELDS

__all__ = [
    "ALGOS",
    "EPISODE_LOG_FIELDS",
    "HeldPolicy",
    "TrainResult",
    "default_algo_kwargs",
    "load_policy",
    "require_sb3",
    "train",
    "wrap_env",
]

ALGOS = ("ppo", "sac")
_EXTRA_MSG = (
    "Stable-Baselines3 is not installed; it is an optional extra: pip install 'afvsgp-gym[rl]'"
)
#: Columns of the per-episode CSV written by :class:`EpisodeLogger`.
EPISODE_LOG_FIELDS = ("timesteps", "env_steps", "wall_s", "worker") + EPISODE_SAFETY_FIELDS
#: Name of the model attribute (saved in the zip) with the training setup.
META_KEY = "afvsgp_meta"


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


def wrap_env(env: Any, learner: str | None = None, filter_kwargs: dict | None = None,
             action_repeat: int = 1) -> Any:
    """``env`` behind ``SafetyFilter(learner, **filter_kwargs)`` (none when ``learner`` is
    None), then :class:`EpisodeSafetyStats`, then :class:`ActionRepeat` (when > 1)."""
    from afvsgp_gym.wrappers import ActionRepeat, EpisodeSafetyStats, SafetyFilter

    if learner is not None:
        env = SafetyFilter(env, learner=learner, **(filter_kwargs or {}))
    env = EpisodeSafetyStats(env)
    if action_repeat > 1:
        env = ActionRepeat(env, action_repeat)
    return env


def default_algo_kwargs(algo: str, timesteps: int, n_envs: int) -> dict[str, Any]:
    """Hyperparameters :func:`train` starts from (``algo_kwargs`` overrides them).

    PPO: rollouts of 256 steps per env (fewer for short runs: a multiple of 64 so no
    mini-batch is truncated), mini-batches of 128 (64 for short runs), 10 epochs, learning
    rate 6e-4, gamma 0.98, two hidden layers of 64 units, initial action std exp(-0.5) =
    0.61 (of the [-1, 1] range; SB3's default 1 saturates half the actions). SAC: a
    300k-transition buffer, learning from 1,000 steps (half the run if shorter), gamma 0.98,
    two layers of 256 units.
    """
    if algo == "ppo":
        n_steps = max(64, min(256, int(timesteps) // n_envs // 64 * 64))
        batch = 128 if n_steps * n_envs >= 512 else 64
        return {"n_steps": n_steps, "batch_size": batch, "n_epochs": 10, "gamma": 0.98,
                "gae_lambda": 0.95, "learning_rate": 6e-4, "ent_coef": 0.0,
                "policy_kwargs": {"net_arch": [64, 64], "log_std_init": -0.5}}
    return {"buffer_size": 300_000, "learning_starts": min(1000, int(timesteps) // 2),
            "batch_size": 256, "gamma": 0.98, "tau": 0.005, "learning_rate": 3e-4,
            "policy_kwargs": {"net_arch": [256, 256]}}


def _episode_logger_class() -> type:
    from stable_baselines3.common.callbacks import BaseCallback

    class EpisodeLogger(BaseCallback):
        """One row per finished episode (``info["episode_safety"]``) to ``csv_path`` and to
        SB3's logger; ``rows`` keeps them."""

        def __init__(self, csv_path: Path | None = None, verbose: int = 0):
            super().__init__(verbose)
            self.csv_path = csv_path
            self.rows: list[dict[str, Any]] = []
            self.env_steps = 0
            self.cumulative_cost = 0
            self.cumulative_cost_after_warmup = 0
            self._fh = None
            self._writer = None
            self._t0 = time.perf_counter()

        def _on_training_start(self) -> None:
            self._t0 = time.perf_counter()
            if self.csv_path is not None:
                self._fh = open(self.csv_path, "w", newline="")  # noqa: SIM115
                self._writer = csv.DictWriter(self._fh, fieldnames=list(EPISODE_LOG_FIELDS))
                self._writer.writeheader()

        def _on_step(self) -> bool:
            for k, info in enumerate(self.locals["infos"]):
                self.env_steps += int(info.get("repeat_steps", 1))
                stats = info.get("episode_safety")
                if stats is None:
                    continue
                row = {"timesteps": int(self.num_timesteps), "env_steps": self.env_steps,
                       "wall_s": round(time.perf_counter() - self._t0, 3), "worker": k}
                row.update(stats)
                row["success"] = int(bool(row["success"]))
                self.rows.append(row)
                self.cumulative_cost += int(stats["cost_steps"])
                self.cumulative_cost_after_warmup += int(stats["cost_steps_after_warmup"])
                if self._writer is not None:
                    self._writer.writerow(row)
                    self._fh.flush()
                log = self.logger
                log.record_mean("rollout/success_rate", float(row["success"]))
                for key in ("cost_steps", "contact_steps", "interventions", "infeasible_steps",
                            "backup_steps", "relaxed_steps", "steps"):
                    log.record_mean(f"safety/ep_{key}", float(stats[key]))
                log.record("safety/cumulative_cost_steps", self.cumulative_cost)
                log.record("safety/cumulative_cost_steps_after_warmup",
                           self.cumulative_cost_after_warmup)
            self.logger.record("safety/env_steps", self.env_steps)
            return True

        def _on_training_end(self) -> None:
            if self._fh is not None:
                self._fh.close()
                self._fh = self._writer = None

    return EpisodeLogger


@dataclass
class TrainResult:
    """Where the model and logs went, and every finished training episode's row."""

    path: Path
    episodes: list[dict[str, Any]] = field(default_factory=list)
    log_dir: Path | None = None
    timesteps: int = 0
    env_steps: int = 0
    wall_time_s: float = 0.0

    @property
    def episode_costs(self) -> list[float]:
        """Steps with cost, per finished episode."""
        return [float(r["cost_steps"]) for r in self.episodes]

    @property
    def episode_interventions(self) -> list[int]:
        """Filter interventions, per finished episode."""
        return [int(r["interventions"]) for r in self.episodes]


def _env_action_repeat(env_id: str, env_kwargs: dict) -> int:
    """The env's suggested ``action_repeat`` (1 when it has none)."""
    import gymnasium as gym

    env = gym.make(env_id, **env_kwargs)
    try:
        return int(getattr(env.unwrapped, "action_repeat", 1))
    finally:
        env.close()


def train(
    algo: str,
    env_id: str,
    *,
    learner: str | None = "afvsgp",
    timesteps: int = 10_000,
    path: str | os.PathLike = "agent.zip",
    seed: int = 0,
    n_envs: int = 1,
    action_repeat: int | None = None,
    env_kwargs: dict | None = None,
    filter_kwargs: dict | None = None,
    algo_kwargs: dict | None = None,
    log_dir: str | os.PathLike | None = None,
    verbose: int = 0,
) -> TrainResult:
    """Train ``algo`` ("ppo" | "sac") on ``env_id`` behind ``SafetyFilter(learner=...)``.

    ``learner=None`` trains on the bare environment (no filter). ``timesteps`` counts the
    agent's steps (each ``action_repeat`` env steps). ``n_envs > 1`` runs the envs in
    ``SubprocVecEnv`` worker processes. ``algo_kwargs`` override :func:`default_algo_kwargs`.
    With ``log_dir``, ``episodes.csv`` (one row per episode) and SB3's ``progress.csv`` are
    written there. The model is saved to ``path`` (``.zip`` added if missing) and reloadable
    with :func:`load_policy`.
    """
    cls = _algo_class(algo)
    algo = algo.lower()
    import torch
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.logger import configure
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    import afvsgp_gym  # noqa: F401  (registers the ids)
    from afvsgp_gym.executors import one_blas_thread

    if isinstance(timesteps, bool) or int(timesteps) < 1:
        raise ValueError(f"timesteps must be a positive integer, got {timesteps}")
    if int(n_envs) < 1:
        raise ValueError(f"n_envs must be a positive integer, got {n_envs}")
    env_kwargs = dict(env_kwargs or {})
    if action_repeat is None:
        action_repeat = _env_action_repeat(env_id, env_kwargs)
    if int(action_repeat) < 1:
        raise ValueError(f"action_repeat must be a positive integer, got {action_repeat}")
    filter_kwargs = dict(filter_kwargs or {})
    wrapper_kwargs = {"learner": learner, "filter_kwargs": filter_kwargs,
                      "action_repeat": int(action_repeat)}
    with one_blas_thread():  # the env worker processes: one BLAS thread each
        venv = make_vec_env(env_id, n_envs=int(n_envs), seed=seed, env_kwargs=env_kwargs,
                            wrapper_class=wrap_env, wrapper_kwargs=wrapper_kwargs,
                            vec_env_cls=SubprocVecEnv if n_envs > 1 else DummyVecEnv)
    kwargs: dict[str, Any] = {"seed": seed, "verbose": verbose, "device": "cpu"}
    kwargs.update(default_algo_kwargs(algo, int(timesteps), int(n_envs)))
    kwargs.update(algo_kwargs or {})
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the workers use the other cores
    csv_path = None
    try:
        model = cls("MlpPolicy", venv, **kwargs)
        if log_dir is not None:
            log_dir = Path(log_dir)
            log_dir.mkdir(parents=True, exist_ok=True)
            formats = ["csv"] + (["stdout"] if verbose else [])
            try:
                import tensorboard  # noqa: F401

                formats.append("tensorboard")
            except ImportError:
                pass
            model.set_logger(configure(str(log_dir), formats))
            csv_path = log_dir / "episodes.csv"
        callback = _episode_logger_class()(csv_path, verbose=verbose)
        t0 = time.perf_counter()
        model.learn(total_timesteps=int(timesteps), callback=callback)
        wall = time.perf_counter() - t0
    finally:
        venv.close()
        torch.set_num_threads(threads)
    setattr(model, META_KEY, {
        "env_id": env_id, "learner": learner, "action_repeat": int(action_repeat),
        "env_kwargs": env_kwargs, "filter_kwargs": filter_kwargs, "seed": int(seed),
        "timesteps": int(model.num_timesteps), "env_steps": int(callback.env_steps),
    })
    path = Path(path)
    if path.suffix != ".zip":
        path = path.with_suffix(path.suffix + ".zip")
    model.save(path)
    return TrainResult(path, callback.rows, log_dir, int(model.num_timesteps),
                       int(callback.env_steps), wall)


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


class HeldPolicy:
    """``obs -> action`` of a loaded model, each action held for ``action_repeat`` calls
    (as :class:`~afvsgp_gym.wrappers.ActionRepeat` does in training); :meth:`reset` at the
    start of an episode (a new policy per episode needs none)."""

    def __init__(self, model: Any, action_repeat: int = 1, deterministic: bool = True):
        self.model = model
        self.action_repeat = int(action_repeat)
        self.deterministic = deterministic
        self.meta = dict(getattr(model, META_KEY, None) or {})
        self.reset()

    def reset(self) -> None:
        self._held: np.ndarray | None = None
        self._age = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        if self._held is None or self._age >= self.action_repeat:
            action, _ = self.model.predict(obs, deterministic=self.deterministic)
            self._held = np.asarray(action, dtype=np.float32)
            self._age = 0
        self._age += 1
        return self._held.copy()


def load_policy(path: str | os.PathLike, *, deterministic: bool = True, env: Any = None,
                action_repeat: int | None = None) -> HeldPolicy:
    """Load a PPO/SAC zip saved by :func:`train` as an ``obs -> action`` callable.

    Each action is held for ``action_repeat`` calls (default: the value the model was trained
    with, 1 for zips without it). With ``env``, its observation and action spaces must match
    the model's (ValueError).
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
    if action_repeat is None:
        action_repeat = int((getattr(model, META_KEY, None) or {}).get("action_repeat", 1))
    if int(action_repeat) < 1:
        raise ValueError(f"action_repeat must be a positive integer, got {action_repeat}")
    return HeldPolicy(model, action_repeat, deterministic)
