"""Choose the self-collision sphere pairs of the Panda and print their table.

Prints ``_KEPT`` of ``afvsgp_gym.envs.self_collision`` (``PANDA_SELF_COLLISION_PAIRS``):

    python benchmarks/select_self_pairs.py

Of the sphere pairs of :data:`~afvsgp_gym.envs.safety_spheres.PANDA_ARM_SPHERES` on
non-adjacent links (:func:`~afvsgp_gym.envs.self_collision.non_adjacent_pairs`), those
overlapping at the ready pose ``Q_HOME`` are left out, and so are those whose clearance ``h``
stays at or above ``SELF_COLLISION_CLEARANCE`` in ``SELECTION_SAMPLES`` joint configurations
drawn uniformly within the model's joint ranges (seed ``SELECTION_SEED``).
tests/envs/test_self_collision.py re-derives the table.
"""

from __future__ import annotations

import mujoco
import numpy as np

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs import self_collision as sc
from afvsgp_gym.envs.safety_spheres import PANDA_ARM_SPHERES, sphere_arrays


def pair_clearances(model: mujoco.MjModel, q: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``h`` (N, C) of the sphere ``pairs`` (C, 2) at each joint configuration ``q`` (N, 7)."""
    data = mujoco.MjData(model)
    bodies, offsets, radii = sphere_arrays(PANDA_ARM_SPHERES)
    ids = np.array([model.body(b).id for b in bodies])
    out = np.empty((len(q), len(pairs)))
    for i, qi in enumerate(q):
        data.qpos[:7] = qi
        mujoco.mj_kinematics(model, data)
        p = data.xpos[ids] + np.einsum("sij,sj->si", data.xmat[ids].reshape(-1, 3, 3), offsets)
        d = p[pairs[:, 0]] - p[pairs[:, 1]]
        out[i] = np.linalg.norm(d, axis=1) - radii[pairs[:, 0]] - radii[pairs[:, 1]]
    return out


def main() -> None:
    model = fm.build_model(fm.PlantParameters(), fm.SceneOptions())
    candidates = sc.non_adjacent_pairs(PANDA_ARM_SPHERES)
    home = pair_clearances(model, fm.Q_HOME[None], candidates)[0]
    lo, hi = model.jnt_range[:7, 0], model.jnt_range[:7, 1]
    rng = np.random.default_rng(sc.SELECTION_SEED)
    q = rng.uniform(lo, hi, (sc.SELECTION_SAMPLES, 7))
    closest = pair_clearances(model, q, candidates).min(axis=0)
    kept = sc.select_pairs(candidates, home, closest)
    print(f"{len(candidates)} candidates, {int((home < 0).sum())} overlapping at home, "
          f"{int(((home >= 0) & (closest >= sc.SELF_COLLISION_CLEARANCE)).sum())} never "
          f"within {sc.SELF_COLLISION_CLEARANCE} m, {len(kept)} kept")
    margin = np.abs(closest - sc.SELF_COLLISION_CLEARANCE)
    print(f"closest sampled minimum to the clearance: {margin.min():.2e} m away; "
          f"smallest home clearance {np.abs(home).min():.2e} m")
    print("_KEPT = {")
    for a in np.unique(kept[:, 0]):
        print(f"    {a}: {tuple(int(b) for b in kept[kept[:, 0] == a, 1])},")
    print("}")


if __name__ == "__main__":
    main()
