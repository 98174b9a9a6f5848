"""Fit the whole-arm safety spheres to the gymnasium-robotics Panda's collision geometry.

Prints the sphere lists of ``afvsgp_gym.envs.safety_spheres.PANDA_ARM_SPHERES`` and
``PANDA_BASE_SPHERES``:

    python benchmarks/fit_safety_spheres.py

Per group of rigidly attached bodies (links 1-6 one each; link 7 with the hand and the fixed
fingers; the base, link0, last, for the self-collision barriers only: 2 spheres, the fewest
of total volume below one's), the surface points of the collision geoms (mesh vertices plus
6000 area-weighted samples per mesh; capsules and boxes sampled on their surfaces) in the
group's body frame are clustered (k-means, 20 restarts), each cluster gets its minimal
enclosing ball (Badoiu-Clarkson iterations), points are reassigned to the ball they fit best
and the balls refitted; the restart with the smallest total volume wins. Every sampled
surface point is inside the union by construction; tests/envs/test_franka.py checks every
mesh vertex (tests/envs/test_self_collision.py the base's).
"""

from __future__ import annotations

import mujoco
import numpy as np

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs.franka import FrankaObstacleEnv

#: (bodies, frame body, number of spheres)
GROUPS = (
    (("panda0_link1",), "panda0_link1", 2),
    (("panda0_link2",), "panda0_link2", 2),
    (("panda0_link3",), "panda0_link3", 2),
    (("panda0_link4",), "panda0_link4", 2),
    (("panda0_link5",), "panda0_link5", 4),
    (("panda0_link6",), "panda0_link6", 2),
    (("panda0_link7", "panda0_leftfinger", "panda0_rightfinger"), "panda0_link7", 7),
    (("panda0_link0",), "panda0_link0", 2),  # PANDA_BASE_SPHERES; last: the others' draws stay
)


def surface_points(m: mujoco.MjModel, g: int, rng: np.random.Generator) -> np.ndarray:
    """Points on the surface of geom ``g`` in its own frame."""
    t = m.geom_type[g]
    if t == mujoco.mjtGeom.mjGEOM_MESH:
        i = m.geom_dataid[g]
        verts = m.mesh_vert[m.mesh_vertadr[i] : m.mesh_vertadr[i] + m.mesh_vertnum[i]]
        faces = m.mesh_face[m.mesh_faceadr[i] : m.mesh_faceadr[i] + m.mesh_facenum[i]]
        a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        idx = rng.choice(len(faces), 6000, p=area / area.sum())
        r1, r2 = np.sqrt(rng.random(6000)), rng.random(6000)
        inside = ((1 - r1)[:, None] * a[idx] + (r1 * (1 - r2))[:, None] * b[idx]
                  + (r1 * r2)[:, None] * c[idx])
        return np.vstack([verts, inside])
    dirs = rng.normal(size=(450, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    size = m.geom_size[g]
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return np.outer(rng.uniform(-size[1], size[1], 450), [0.0, 0.0, 1.0]) + size[0] * dirs
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * size
    raise ValueError(f"geom type {t} not handled")


def group_points(env: FrankaObstacleEnv, bodies, frame: str, rng) -> np.ndarray:
    m, d = env.model, env.data
    fb = m.body(frame).id
    rot, pos = d.xmat[fb].reshape(3, 3), d.xpos[fb]
    out = []
    for g in np.concatenate([fm.base_collision_geoms(m), fm.arm_collision_geoms(m)]):
        if m.body(m.geom_bodyid[g]).name in bodies:
            world = d.geom_xpos[g] + surface_points(m, g, rng) @ d.geom_xmat[g].reshape(3, 3).T
            out.append((world - pos) @ rot)
    return np.vstack(out)


def min_ball(points: np.ndarray, iters: int = 1000) -> tuple[np.ndarray, float]:
    c = points.mean(axis=0)
    for i in range(1, iters):
        far = points[np.argmax(((points - c) ** 2).sum(axis=1))]
        c = c + (far - c) / (i + 1)
    return c, float(np.sqrt(((points - c) ** 2).sum(axis=1)).max())


def fit(points: np.ndarray, k: int, restarts: int = 20) -> list[tuple[np.ndarray, float]]:
    best, best_cost = None, np.inf
    for seed in range(restarts):
        rng = np.random.default_rng(seed)
        centres = points[rng.choice(len(points), k, replace=False)]
        for _ in range(30):
            lab = np.argmin(((points[:, None] - centres[None]) ** 2).sum(axis=2), axis=1)
            centres = np.array([points[lab == j].mean(axis=0) if np.any(lab == j)
                                else centres[j] for j in range(k)])
        balls = [min_ball(points[lab == j]) for j in range(k) if np.any(lab == j)]
        for _ in range(10):
            cs = np.array([b[0] for b in balls])
            rs = np.array([b[1] for b in balls])
            lab = np.argmin(np.sqrt(((points[:, None] - cs[None]) ** 2).sum(axis=2)) - rs, axis=1)
            balls = [min_ball(points[lab == j]) for j in range(len(balls)) if np.any(lab == j)]
        cost = sum(r**3 for _, r in balls)
        if cost < best_cost:
            best, best_cost = balls, cost
    return best


def main() -> None:
    env = FrankaObstacleEnv("static")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for bodies, frame, k in GROUPS:
        if bodies == ("panda0_link0",):
            print("PANDA_BASE_SPHERES:")
        for c, r in fit(group_points(env, bodies, frame, rng), k):
            print(f'    _s("{frame.removeprefix("panda0_")}", {c[0]:.4f}, {c[1]:.4f}, '
                  f'{c[2]:.4f}, {r:.4f}),')


if __name__ == "__main__":
    main()
