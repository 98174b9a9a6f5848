"""Record a filtered episode to mp4 (imageio-ffmpeg) or gif, headless (``MUJOCO_GL=egl``).

One public function, :func:`record_video`: make the env with ``render_mode="rgb_array"``, wrap it
in :class:`afvsgp_gym.wrappers.SafetyFilter`, run the agent, write ``env.render()`` frames.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["VIDEO_SUFFIXES", "record_video"]

VIDEO_SUFFIXES = (".mp4", ".gif")


def record_video(
    env_id: str,
    path: str | os.PathLike,
    *,
    agent: str = "nominal",
    learner: str | None = "afvsgp",
    seed: int = 0,
    max_steps: int | None = None,
    every: int = 1,
    fps: float | None = None,
    env_kwargs: dict | None = None,
    filter_kwargs: dict | None = None,
) -> dict[str, Any]:
    """Record one episode; returns ``{"path", "frames", "steps", "min_h", "violation_steps"}``.

    ``every`` keeps one frame in ``every`` steps (the video plays at ``render_fps / every``
    unless ``fps`` is given). The suffix of ``path`` picks the format: ``.mp4`` or ``.gif``.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    import gymnasium as gym
    import imageio.v2 as imageio

    import afvsgp_gym  # noqa: F401
    from afvsgp_gym.evaluation import make_policy

    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"path must end in one of {', '.join(VIDEO_SUFFIXES)}, got {str(path)!r}")
    if every < 1:
        raise ValueError(f"every must be a positive integer, got {every}")
    env = gym.make(env_id, render_mode="rgb_array", **(env_kwargs or {}))
    if learner is not None:
        from afvsgp_gym.wrappers import SafetyFilter

        env = SafetyFilter(env, learner=learner, **{"seed": seed, **(filter_kwargs or {})})
    render_fps = float(env.metadata.get("render_fps") or 1.0 / float(env.unwrapped.dt))
    fps = float(fps) if fps is not None else max(render_fps / every, 1.0)
    policy = make_policy(agent, env, seed=seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    kwargs: dict[str, Any] = {"fps": fps}
    if path.suffix.lower() == ".mp4":
        kwargs.update(codec="libx264", macro_block_size=1, quality=7)
    else:
        kwargs = {"duration": 1.0 / fps, "loop": 0}
    frames = steps = violations = 0
    min_h = np.inf
    try:
        obs, _ = env.reset(seed=seed)
        with imageio.get_writer(path, **kwargs) as writer:
            writer.append_data(_frame(env.render()))
            frames += 1
            while True:
                obs, _, terminated, truncated, info = env.step(policy(obs))
                steps += 1
                h = float(info.get("h", np.nan))
                violations += int(h < 0)
                min_h = min(min_h, h)
                if steps % every == 0:
                    writer.append_data(_frame(env.render()))
                    frames += 1
                if terminated or truncated or (max_steps is not None and steps >= max_steps):
                    break
    finally:
        env.close()
    return {"path": path, "frames": frames, "steps": steps, "min_h": float(min_h),
            "violation_steps": violations}


def _frame(img: Any) -> np.ndarray:
    if img is None:
        raise RuntimeError("env.render() returned None: the env was not made with "
                           "render_mode='rgb_array'")
    return np.ascontiguousarray(np.asarray(img, dtype=np.uint8))
