"""Policies built to break a safety filter on the Franka torque envs.

Each is a callable ``obs -> action`` made from the (possibly wrapped) env, like
:class:`~afvsgp_gym.agents.NominalController`; they read ``env.unwrapped`` for the kinematics
(and the greedy one for the true model), never the filter:

- :class:`TaskSpaceRam`: a stiff Jacobian-transpose spring that drives the hand into the
  nearest obstacle (no damping, no gravity model: it overshoots and rams);
- :class:`JointSwing`: full-torque bang-bang swings of one joint, the others damped;
- :class:`UniformRandom`: uniform samples of the action space;
- :class:`GreedyDescent`: the action (a vertex of the box) that makes the smallest obstacle
  barrier fall fastest, ``u = -sign(lg)`` of the true ``h'' = lf + lg u``, and past the
  obstacles the joint-limit barriers likewise;
- :func:`untrained_sb3`: a freshly initialised Stable-Baselines3 PPO policy, sampled
  stochastically (what an RL agent does in its first rollouts; needs the ``rl`` extra).

:data:`ADVERSARIAL_AGENTS` maps the names ``--agent`` and sweep configs accept to them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = [
    "ADVERSARIAL_AGENTS",
    "GreedyDescent",
    "JointSwing",
    "TaskSpaceRam",
    "UniformRandom",
    "untrained_sb3",
]


def _franka(env: Any, name: str) -> Any:
    base = env.unwrapped
    if not (hasattr(base, "model") and hasattr(base, "q_home") and hasattr(base, "obstacles")):
        raise ValueError(f"agent {name!r} needs a Franka torque env (afvsgp_gym/FrankaObstacle*"
                         f"), got {type(base).__name__}")
    if tuple(env.action_space.shape) != (7,):
        raise ValueError(f"agent {name!r} needs the 7 joint torques as the action, got "
                         f"{env.action_space}")
    return base


class TaskSpaceRam:
    """``tau = J_ee' k (p_o - p_ee)``: a spring of stiffness ``stiffness`` (N/m) pulling the
    end-effector at the centre of the nearest obstacle, with no damping (it overshoots into
    it), clipped to the torque limits."""

    def __init__(self, env: Any, stiffness: float = 400.0, seed: int | None = None) -> None:
        import mujoco

        base = _franka(env, "ram")
        self._mj, self.model = mujoco, base.model
        self.data = mujoco.MjData(self.model)
        self.site = self.model.site("end_effector").id
        self.stiffness = float(stiffness)
        self.scale = np.asarray(base.action_scale, dtype=np.float64)
        self.n_obstacles = int(base.n_obstacles)
        self.jac = np.zeros((3, self.model.nv))
        self.low = np.asarray(env.action_space.low, dtype=np.float64)
        self.high = np.asarray(env.action_space.high, dtype=np.float64)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        mj, m, d = self._mj, self.model, self.data
        obs = np.asarray(obs, dtype=np.float64)
        d.qpos[:] = obs[:7]
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        mj.mj_jacSite(m, d, self.jac, None, self.site)
        p = obs[14:17]
        centres = obs[20 : 20 + 3 * self.n_obstacles].reshape(-1, 3)
        target = centres[np.argmin(np.linalg.norm(centres - p, axis=1))]
        tau = self.jac.T @ (self.stiffness * (target - p))
        return np.clip(tau / self.scale, self.low, self.high)


class JointSwing:
    """Full torque on ``joint`` (1-7), its sign switching every ``half_period`` s (a
    bang-bang swing), the other joints damped (``u = -damping q'``, clipped)."""

    def __init__(self, env: Any, joint: int = 1, half_period: float = 1.0,
                 damping: float = 1.0, seed: int | None = None) -> None:
        base = _franka(env, f"swing{joint}")
        if not (isinstance(joint, int) and 1 <= joint <= 7):
            raise ValueError(f"joint must be 1-7, got {joint!r}")
        self.joint = joint - 1
        self.steps_per_half = max(1, int(round(float(half_period) / float(base.dt))))
        self.damping = float(damping)
        self.low = np.asarray(env.action_space.low, dtype=np.float64)
        self.high = np.asarray(env.action_space.high, dtype=np.float64)
        # a seed picks the first direction (episodes differ in more than their reset noise)
        self.sign = -1.0 if seed is not None and seed % 2 else 1.0
        self.t = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        qd = np.asarray(obs[7:14], dtype=np.float64)
        u = np.clip(-self.damping * qd, -1.0, 1.0)
        phase = (self.t // self.steps_per_half) % 2
        u[self.joint] = self.sign * (1.0 if phase == 0 else -1.0)
        self.t += 1
        return np.clip(u * self.high, self.low, self.high)


class UniformRandom:
    """Uniform samples of the action space, seeded."""

    def __init__(self, env: Any, seed: int | None = None) -> None:
        self.space = env.action_space
        self.space.seed(seed)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.space.sample()


class GreedyDescent:
    """The box vertex that decreases the smallest obstacle barrier fastest under the true
    model: ``u = -sign(lg_k)`` for ``k`` the obstacle barrier of smallest ``h`` (and with
    no obstacle barrier within ``reach`` m, the joint-limit barrier of smallest ``h``)."""

    def __init__(self, env: Any, reach: float = 0.3, seed: int | None = None) -> None:
        self.base = _franka(env, "greedy")
        self.reach = float(reach)
        self.low = np.asarray(env.action_space.low, dtype=np.float64)
        self.high = np.asarray(env.action_space.high, dtype=np.float64)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        base = self.base
        terms = base.barrier_terms("true")
        h = terms.h
        n_obs = base.n_obstacle_barriers
        k = int(np.argmin(h[:n_obs]))
        limit = n_obs + base.n_self_collision_barriers  # the first joint-limit barrier
        if h[k] > self.reach and len(h) > limit:
            k = limit + int(np.argmin(h[limit:]))
        g = terms.lg[k]
        return np.where(g > 0, self.low, self.high)


def untrained_sb3(env: Any, seed: int | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """A freshly initialised PPO ``MlpPolicy`` (seeded), sampled stochastically."""
    from afvsgp_gym.agents.sb3 import require_sb3

    require_sb3()
    from stable_baselines3 import PPO

    model = PPO("MlpPolicy", env, seed=seed, device="cpu")
    low, high = env.action_space.low, env.action_space.high

    def act(obs: np.ndarray) -> np.ndarray:
        action, _ = model.predict(obs, deterministic=False)
        return np.clip(action, low, high)

    return act


def _swing(joint: int) -> Callable[..., Any]:
    def make(env: Any, seed: int | None = None) -> JointSwing:
        return JointSwing(env, joint=joint, seed=seed)

    make.__doc__ = f"Bang-bang swings of joint {joint} (:class:`JointSwing`)."
    return make


#: Agent name -> ``factory(env, seed=...) -> policy``.
ADVERSARIAL_AGENTS: dict[str, Callable[..., Any]] = {
    "ram": TaskSpaceRam,
    **{f"swing{j}": _swing(j) for j in range(1, 8)},
    "greedy": GreedyDescent,
    "untrained-ppo": untrained_sb3,
}
