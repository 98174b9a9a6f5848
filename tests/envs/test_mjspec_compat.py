"""MjSpec joint setters on the installed MuJoCo: the compiled model has the values set."""

import mujoco
import numpy as np
import pytest

from afvsgp_gym.envs import franka_model as fm
from afvsgp_gym.envs.mjspec_compat import set_linear_coefficient

# A joint whose MJCF already carries damping, friction and armature: on MuJoCo >= 3.7 a second
# damping coefficient (quadratic term) is given too, which the setter must clear.
_ONE_JOINT = """<mujoco><worldbody><body>
  <joint name="j" type="hinge" damping="{damping}" frictionloss="3" armature="0.5"/>
  <geom size="0.1" mass="1"/>
</body></worldbody></mujoco>"""


def _quadratic_terms(model: mujoco.MjModel) -> np.ndarray:
    """Higher-order damping coefficients (a field of MuJoCo >= 3.7; none before)."""
    return getattr(model, "dof_dampingpoly", np.zeros((model.nv, 0)))


def _one_joint_spec() -> mujoco.MjSpec:
    vector_form = np.ndim(mujoco.MjSpec().worldbody.add_body().add_joint().damping) > 0
    return mujoco.MjSpec.from_string(_ONE_JOINT.format(damping="5 7" if vector_form else "5"))


def test_source_values_compile_as_written():
    model = _one_joint_spec().compile()
    assert model.dof_damping[0] == 5.0 and model.dof_frictionloss[0] == 3.0
    assert model.dof_armature[0] == 0.5


@pytest.mark.parametrize("value", [0.0, 1.25, np.float64(2.5), np.array(4.0)])
def test_linear_coefficients_replace_the_source_values(value):
    spec = _one_joint_spec()
    joint = spec.joint("j")
    for attribute in ("damping", "frictionloss", "armature"):
        set_linear_coefficient(joint, attribute, value)
    model = spec.compile()
    assert model.dof_damping[0] == float(value)
    assert model.dof_frictionloss[0] == float(value)
    assert model.dof_armature[0] == float(value)
    np.testing.assert_array_equal(_quadratic_terms(model), 0.0)


def test_build_model_sets_each_joints_damping_friction_and_armature():
    params = fm.PlantParameters(
        damping=np.linspace(0.5, 3.5, 7),
        frictionloss=np.linspace(0.1, 0.7, 7),
        armature=np.linspace(0.01, 0.07, 7),
    )
    model = fm.build_model(params, fm.SceneOptions())
    dofs = [model.joint(name).dofadr[0] for name in fm.JOINTS]
    np.testing.assert_array_equal(model.dof_damping[dofs], params.damping)
    np.testing.assert_array_equal(model.dof_frictionloss[dofs], params.frictionloss)
    np.testing.assert_array_equal(model.dof_armature[dofs], params.armature)
    # the source MJCF's servo damping (100 / 10 Nm s/rad) is gone, no higher-order term added
    np.testing.assert_array_equal(_quadratic_terms(model)[dofs], 0.0)
