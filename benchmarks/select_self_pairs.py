"""Choose the self-collision sphere pairs of the Panda: print their table, write the minima.

Prints ``_KEPT`` of ``afvsgp_gym.envs.self_collision`` (``PANDA_SELF_COLLISION_PAIRS``) and
writes every candidate's clearances to ``benchmarks/results/self_pairs.json``:

    python benchmarks/select_self_pairs.py

The candidates are the pairs of ``PANDA_SELF_COLLISION_SPHERES`` (the arm's spheres and the
base's, which do not move) on non-adjacent links
(:func:`~afvsgp_gym.envs.self_collision.non_adjacent_pairs`; the base's with link2 are
candidates, two links apart). Left out: those overlapping at the ready pose ``Q_HOME``, and
those whose clearance ``h`` cannot come below ``SELF_COLLISION_CLEARANCE`` anywhere within
the model's joint ranges. Each candidate's smallest ``h`` over that box is found in two
stages:

1. ``SELECTION_SAMPLES`` joint configurations drawn uniformly within the ranges (seed
   ``SELECTION_SEED``): the sampled minimum;
2. L-BFGS-B (scipy; bounds the joint ranges, the exact gradient ``n'(J_a - J_b)``) from the
   ``REFINE_STARTS`` sampled configurations where that pair's ``h`` was smallest: the refined
   minimum, the least of the runs and never above the sampled one.

Deterministic: the draws are seeded and L-BFGS-B draws nothing, so a rerun on the same
versions writes the same file. ``self_pairs.json`` holds, per candidate, ``h`` at the ready
pose, the sampled and the refined minimum and the configuration attaining the refined one;
tests/envs/test_self_collision.py checks the table against it and re-checks it in part.
"""

from __future__ import annotations

import json
import pathlib

import mujoco
import numpy as np
from scipy.optimize import minimize

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs import self_collision as sc
from afvsgp_gym.envs.safety_spheres import sphere_arrays

RESULTS = pathlib.Path(__file__).parent / "results" / "self_pairs.json"
SPHERES = sc.PANDA_SELF_COLLISION_SPHERES


def build() -> mujoco.MjModel:
    return fm.build_model(fm.PlantParameters(), fm.SceneOptions())


class PairClearance:
    """``h`` of sphere pairs of :data:`SPHERES` as a function of the joint configuration,
    and its gradient (for the minimiser)."""

    def __init__(self, model: mujoco.MjModel):
        self.model, self.data = model, mujoco.MjData(model)
        bodies, self.offsets, self.radii = sphere_arrays(SPHERES)
        self.ids = np.array([model.body(b).id for b in bodies])

    def centres(self, q: np.ndarray) -> np.ndarray:
        d = self.data
        d.qpos[:7] = q
        mujoco.mj_kinematics(self.model, d)
        rot = d.xmat[self.ids].reshape(-1, 3, 3)
        return d.xpos[self.ids] + np.einsum("sij,sj->si", rot, self.offsets)

    def values(self, q: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """``h`` (N, C) of the ``pairs`` (C, 2) at each configuration ``q`` (N, 7)."""
        r = self.radii[pairs[:, 0]] + self.radii[pairs[:, 1]]
        out = np.empty((len(q), len(pairs)))
        for i, qi in enumerate(q):
            p = self.centres(qi)
            out[i] = np.linalg.norm(p[pairs[:, 0]] - p[pairs[:, 1]], axis=1) - r
        return out

    def value_and_gradient(self, q: np.ndarray, a: int, b: int) -> tuple[float, np.ndarray]:
        """``h`` of the pair ``(a, b)`` at ``q`` (7,) and ``dh/dq = n'(J_a - J_b)``."""
        m, d = self.model, self.data
        p = self.centres(q)
        mujoco.mj_comPos(m, d)
        diff = p[a] - p[b]
        dist = float(np.linalg.norm(diff))
        jac_a, jac_b = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jac_a, None, p[a], int(self.ids[a]))
        mujoco.mj_jac(m, d, jac_b, None, p[b], int(self.ids[b]))
        grad = (diff / dist) @ (jac_a - jac_b)
        return dist - self.radii[a] - self.radii[b], grad[:7]


def refine(clearance: PairClearance, pair: tuple[int, int], starts: np.ndarray
           ) -> tuple[float, np.ndarray]:
    """The least ``h`` of ``pair`` found by L-BFGS-B within the joint ranges from each of
    ``starts`` (K, 7), and where."""
    m = clearance.model
    bounds = list(zip(m.jnt_range[:7, 0], m.jnt_range[:7, 1], strict=True))
    best, where = np.inf, None
    for q0 in starts:
        res = minimize(clearance.value_and_gradient, q0, args=pair, jac=True,
                       method="L-BFGS-B", bounds=bounds)
        q = np.clip(res.x, m.jnt_range[:7, 0], m.jnt_range[:7, 1])
        h = float(clearance.values(q[None], np.array([pair]))[0, 0])
        if h < best:
            best, where = h, q
    return best, where


def samples(model: mujoco.MjModel) -> np.ndarray:
    """The seeded configurations (SELECTION_SAMPLES, 7) within the joint ranges."""
    rng = np.random.default_rng(sc.SELECTION_SEED)
    return rng.uniform(model.jnt_range[:7, 0], model.jnt_range[:7, 1],
                       (sc.SELECTION_SAMPLES, 7))


def main() -> None:
    model = build()
    clearance = PairClearance(model)
    candidates = sc.non_adjacent_pairs(SPHERES)
    home = clearance.values(fm.Q_HOME[None], candidates)[0]
    h = clearance.values(samples(model), candidates)
    sampled = h.min(axis=0)
    q = samples(model)
    refined, witness = np.empty(len(candidates)), np.empty((len(candidates), 7))
    for c, (a, b) in enumerate(candidates):
        best = np.argsort(h[:, c], kind="stable")[: sc.REFINE_STARTS]
        refined[c], witness[c] = refine(clearance, (int(a), int(b)), q[best])
        refined[c] = min(refined[c], sampled[c])  # never above the sampled minimum
        if refined[c] == sampled[c]:
            witness[c] = q[best[0]]
    kept = sc.select_pairs(candidates, home, refined)
    far = (home >= 0) & (refined >= sc.SELF_COLLISION_CLEARANCE)
    print(f"{len(candidates)} candidates, {int((home < 0).sum())} overlapping at home, "
          f"{int(far.sum())} never within {sc.SELF_COLLISION_CLEARANCE} m (refined), "
          f"{len(kept)} kept; sampled minima below it: "
          f"{int(((home >= 0) & (sampled < sc.SELF_COLLISION_CLEARANCE)).sum())}")
    margin = np.abs(refined - sc.SELF_COLLISION_CLEARANCE)
    print(f"closest refined minimum to the clearance: {margin.min():.2e} m away; smallest "
          f"home clearance {np.abs(home).min():.2e} m; refinement lowered the minimum by up "
          f"to {(sampled - refined).max():.3f} m")
    head = json.dumps({"clearance": sc.SELF_COLLISION_CLEARANCE,
                       "samples": sc.SELECTION_SAMPLES, "seed": sc.SELECTION_SEED,
                       "refine_starts": sc.REFINE_STARTS})
    rows = [json.dumps({"pair": [int(a), int(b)], "home": float(home[c]),
                        "sampled": float(sampled[c]), "refined": float(refined[c]),
                        "q": [float(x) for x in witness[c]]})
            for c, (a, b) in enumerate(candidates)]
    RESULTS.write_text(head[:-1] + ', "pairs": [\n' + ",\n".join(rows) + "\n]}\n")
    print("_KEPT = {")
    for a in np.unique(kept[:, 0]):
        print(f"    {a}: {tuple(int(b) for b in kept[kept[:, 0] == a, 1])},")
    print("}")


if __name__ == "__main__":
    main()
