"""MuJoCo model of a torque-controlled Franka Panda, assembled at run time with MjSpec.

The kinematic chain, meshes and link masses come from the Panda MJCF shipped in the installed
``gymnasium_robotics`` package (``envs/assets/kitchen_franka/franka_assets``, Apache-2.0,
from vikashplus/franka); nothing is downloaded. Changes made here:

- The position servos are replaced by ``motor`` actuators on the 7 arm joints with gear =
  Franka's torque limits (87 Nm joints 1-4, 12 Nm joints 5-7) and ctrlrange [-1, 1], so
  ``ctrl = tau / tau_max`` and the normalised action is the control.
- The finger joints are removed (gripper fixed, fingers rigid with the hand).
- The servo-level joint damping of the source (100 / 10 Nm s/rad) is replaced by the plant's
  ``damping``, ``frictionloss`` and rotor ``armature``.
- Gravity compensation as on the real robot: the controller's torques act on top of the
  robot's own compensation of its *nominal* (catalogue) model. MuJoCo applies
  ``gravcomp * m_body * g`` per body, so each link of the true plant gets
  ``gravcomp = m_nominal / m_true`` (it must be set in the MjSpec before compiling; changing
  ``model.body_gravcomp`` afterwards has no effect when the compiled model had none). The
  payload body (at the flange) has gravcomp 0. The residual gravity is
  ``(m_true - m_nominal) g`` per link plus the full payload weight: part of the unknown
  dynamics the filter has to learn.
- Contacts are disabled in the physics (obstacles are non-physical visual spheres); collisions
  are detected geometrically (``mj_geomDistance``), so contact forces never enter the dynamics
  and the "true" barrier terms stay exact.
"""

from __future__ import annotations

import functools
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import mujoco
import numpy as np

from afvsgp_gym.envs.mjspec_compat import set_linear_coefficient
from afvsgp_gym.envs.primitives import Box, Capsule
from afvsgp_gym.envs.scenario import ObstacleSpec

ARM_BODIES = tuple(f"panda0_link{i}" for i in range(1, 8))
HAND_BODIES = ("panda0_leftfinger", "panda0_rightfinger")
JOINTS = tuple(f"robot:panda0_joint{i}" for i in range(1, 8))
TAU_MAX = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
EE_SITE = "end_effector"
EE_BODY = "panda0_link7"
#: Ready pose: hand pointing down, end-effector about (0.307, 0, 0.487) m.
Q_HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 0.0, 0.785])
#: Flange (hand mounting plane) position in the link7 frame.
FLANGE_POS = np.array([0.0, 0.0, 0.107])


def asset_dir() -> str:
    """Folder of the Panda MJCF inside the installed gymnasium_robotics package."""
    import importlib.util

    spec = importlib.util.find_spec("gymnasium_robotics")
    if spec is None or spec.origin is None:  # pragma: no cover - dependency of the package
        raise ImportError("gymnasium_robotics is required for the Franka environments")
    root = os.path.dirname(spec.origin)
    return os.path.join(root, "envs", "assets", "kitchen_franka", "franka_assets")


@functools.lru_cache(maxsize=1)
def _base_xml() -> str:
    """MJCF string of the arm (no actuators, no finger joints), absolute mesh paths."""
    root = asset_dir()
    assets = ET.parse(os.path.join(root, "assets.xml")).getroot()
    chain = ET.parse(os.path.join(root, "chain.xml")).getroot()
    for parent in chain.iter():
        for child in list(parent):
            if child.tag == "joint" and "finger" in child.get("name", ""):
                parent.remove(child)
    inner_assets = "".join(
        ET.tostring(c, encoding="unicode") for c in assets if c.tag in ("asset", "default")
    )
    inner_chain = "".join(ET.tostring(c, encoding="unicode") for c in chain)
    meshdir = os.path.join(root, "meshes")
    return f"""<mujoco model="afvsgp_panda">
  <compiler angle="radian" meshdir="{meshdir}" autolimits="true"/>
  <option timestep="0.001" integrator="implicitfast"><flag contact="disable"/></option>
  <visual><global offwidth="640" offheight="640"/><quality shadowsize="1024"/></visual>
  {inner_assets}
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".25 .3 .35" rgb2=".15 .2 .25"
      width="256" height="256"/>
    <material name="grid" texture="grid" texrepeat="4 4" reflectance="0.1"/>
  </asset>
  <worldbody>
    <light pos="1 1 3" dir="-1 -1 -3" diffuse=".8 .8 .8"/>
    <light pos="1 -1 3" dir="-1 1 -3" diffuse=".5 .5 .5"/>
    <geom name="floor" type="plane" size="2 2 0.1" material="grid" contype="0" conaffinity="0"/>
    {inner_chain}
  </worldbody>
</mujoco>"""


@functools.lru_cache(maxsize=1)
def catalogue_inertials() -> dict[str, tuple[float, np.ndarray, np.ndarray, np.ndarray]]:
    """Nominal (catalogue) mass, diagonal inertia, ipos, iquat of each moving body."""
    model = mujoco.MjSpec.from_string(_base_xml()).compile()
    out = {}
    for name in ARM_BODIES + HAND_BODIES:
        b = model.body(name)
        out[name] = (float(b.mass[0]), b.inertia.copy(), b.ipos.copy(), b.iquat.copy())
    return out


@dataclass(frozen=True)
class PlantParameters:
    """Physical parameters of one Panda model (true plant or a nominal model).

    ``mass_scale`` scales mass and inertia of each of the 9 moving bodies (7 links, 2 fingers)
    relative to the catalogue; ``nominal_mass_scale`` is what the robot's own gravity
    compensation believes (1 = catalogue).
    """

    mass_scale: np.ndarray = field(default_factory=lambda: np.ones(9))
    payload_mass: float = 0.0
    damping: np.ndarray = field(default_factory=lambda: np.zeros(7))
    frictionloss: np.ndarray = field(default_factory=lambda: np.zeros(7))
    armature: np.ndarray = field(default_factory=lambda: np.zeros(7))
    nominal_mass_scale: np.ndarray = field(default_factory=lambda: np.ones(9))


@dataclass(frozen=True)
class ObstacleGeom:
    """The MuJoCo geom of a non-sphere obstacle: ``kind`` ``"box"``, ``"capsule"`` or
    ``"plane"``, MuJoCo's ``size`` (box: half sizes; capsule: radius, half length along its
    local z; plane: half extents of the drawn rectangle and grid spacing, the collision
    plane being infinite) and ``quat`` (w, x, y, z) of the geom in its obstacle body."""

    kind: str
    size: tuple[float, float, float]
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)


#: Half extent (m) of the rectangle drawn for a plane obstacle (its barrier and contact check
#: use the infinite plane).
PLANE_DRAW_HALF_EXTENT = 1.0


def obstacle_geom(ob: ObstacleSpec) -> ObstacleGeom | None:
    """The MuJoCo geom of a non-sphere obstacle (None for a sphere): a box's half sizes and
    rotation, a capsule's radius and half length along its local z turned onto its axis, a
    plane's drawn rectangle with its z along the normal (the simulation's and the robot
    stand-in's)."""
    shape = ob.shape
    if shape is None:
        return None
    quat = np.empty(4)
    if isinstance(shape, Box):
        mujoco.mju_mat2Quat(quat, np.ascontiguousarray(shape.rotation, dtype=np.float64).ravel())
        return ObstacleGeom("box", tuple(shape.half_sizes.tolist()), tuple(quat.tolist()))
    axis = shape.axis if isinstance(shape, Capsule) else shape.normal
    mujoco.mju_quatZ2Vec(quat, np.array(axis, dtype=np.float64))
    if isinstance(shape, Capsule):
        return ObstacleGeom("capsule", (shape.radius, shape.half_length, 0.0),
                            tuple(quat.tolist()))
    half = PLANE_DRAW_HALF_EXTENT
    return ObstacleGeom("plane", (half, half, 0.05), tuple(quat.tolist()))


_GEOM_TYPES = {"box": mujoco.mjtGeom.mjGEOM_BOX, "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
               "plane": mujoco.mjtGeom.mjGEOM_PLANE}


@dataclass(frozen=True)
class SceneOptions:
    """Non-physical scene elements: obstacle spheres, reference marker, EE sphere.
    ``obstacle_geoms[i]`` (when given and not None) replaces obstacle i's sphere of radius
    ``obstacle_radii[i]``."""

    obstacle_radii: tuple[float, ...] = (0.05,)
    ee_radius: float = 0.05
    physics_dt: float = 0.001
    obstacle_geoms: tuple[ObstacleGeom | None, ...] = ()


def build_model(params: PlantParameters, scene: SceneOptions) -> mujoco.MjModel:
    """Compile the Panda with torque actuators, gravity compensation and the scene."""
    spec = mujoco.MjSpec.from_string(_base_xml())
    spec.option.timestep = scene.physics_dt
    cat = catalogue_inertials()
    for k, name in enumerate(ARM_BODIES + HAND_BODIES):
        mass, inertia, ipos, iquat = cat[name]
        scale = float(params.mass_scale[k])
        body = spec.body(name)
        body.explicitinertial = True
        body.mass = mass * scale
        body.inertia = inertia * scale
        body.ipos = ipos
        body.iquat = iquat
        # robot's compensation of its nominal weight, as a fraction of the true weight
        body.gravcomp = float(params.nominal_mass_scale[k]) / scale
    for geom in spec.geoms:
        geom.mass = 0.0
        geom.density = 0.0
    for i, name in enumerate(JOINTS):
        joint = spec.joint(name)
        set_linear_coefficient(joint, "damping", params.damping[i])
        set_linear_coefficient(joint, "frictionloss", params.frictionloss[i])
        set_linear_coefficient(joint, "armature", params.armature[i])
        act = spec.add_actuator()
        act.name = f"tau{i + 1}"
        act.target = name
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.set_to_motor()
        act.gear = [float(TAU_MAX[i]), 0, 0, 0, 0, 0]
        act.ctrllimited = True
        act.ctrlrange = [-1.0, 1.0]
    link7 = spec.body(EE_BODY)
    if params.payload_mass > 0:
        r = 0.04  # solid sphere of radius 4 cm just above the hand mount
        pay = link7.add_body()
        pay.name = "payload"
        pay.pos = FLANGE_POS + np.array([0.0, 0.0, 0.02])
        pay.explicitinertial = True
        pay.mass = float(params.payload_mass)
        pay.inertia = [0.4 * params.payload_mass * r * r] * 3
        pay.gravcomp = 0.0
        g = pay.add_geom()
        g.type = mujoco.mjtGeom.mjGEOM_SPHERE
        g.size = [r, 0, 0]
        g.rgba = [0.9, 0.6, 0.1, 1.0]
        g.contype = g.conaffinity = 0
    ee = spec.site(EE_SITE)
    s = link7.add_site()
    s.name = "ee_sphere"
    s.pos = ee.pos
    s.type = mujoco.mjtGeom.mjGEOM_SPHERE
    s.size = [scene.ee_radius, 0, 0]
    s.rgba = [0.2, 0.4, 1.0, 0.3]
    for i, radius in enumerate(scene.obstacle_radii):
        body = spec.worldbody.add_body()
        body.name = f"obstacle{i}"
        body.mocap = True
        body.pos = [2.0 + i, 2.0, 0.0]
        g = body.add_geom()
        g.name = f"obstacle{i}"
        shape = scene.obstacle_geoms[i] if i < len(scene.obstacle_geoms) else None
        if shape is None:
            g.type = mujoco.mjtGeom.mjGEOM_SPHERE
            g.size = [radius, 0, 0]
        else:
            g.type = _GEOM_TYPES[shape.kind]
            g.size = list(shape.size)
            g.quat = list(shape.quat)
        g.rgba = [0.6, 0.45, 0.3, 0.5] if shape is not None and shape.kind == "plane" else [
            0.9, 0.15, 0.15, 0.6]
        g.contype = g.conaffinity = 0
    ref = spec.worldbody.add_body()
    ref.name = "reference"
    ref.mocap = True
    g = ref.add_geom()
    g.type = mujoco.mjtGeom.mjGEOM_SPHERE
    g.size = [0.015, 0, 0]
    g.rgba = [0.1, 0.8, 0.2, 0.9]
    g.contype = g.conaffinity = 0
    return spec.compile()


def arm_collision_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Ids of the arm's collision geoms (meshes of class panda_col and finger primitives)."""
    ids = []
    first_link = model.body(ARM_BODIES[0]).id
    for g in range(model.ngeom):
        body = model.geom_bodyid[g]
        if body >= first_link and model.geom_group[g] == 3:
            ids.append(g)
    return np.array(ids, dtype=int)


def base_collision_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Ids of the base's (link0's) collision geoms: it does not move, and
    :func:`arm_collision_geoms` leaves it out."""
    base = model.body("panda0_link0").id
    return np.flatnonzero((model.geom_bodyid == base) & (model.geom_group == 3))
