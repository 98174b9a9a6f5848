"""Build of the optional compiled cores (the rest of the metadata is in pyproject.toml).

``afvsgp_gym.cbf._cones`` (the certified several-cones fast path of the filter's cone program),
``afvsgp_gym.cbf._step`` (the controller's cone matrices, exploration gate, step glue) and
``afvsgp_gym.gp._bank`` (the per-step arithmetic of the AFVSGP learners; it calls the BLAS and
LAPACK that scipy ships, found at import) and ``afvsgp_gym.robots._arm`` (the Franka bridge's
sphere kinematics and pair terms) are optional: without a C compiler the build goes
on and the package uses its numpy paths. All take their arguments through afvsgp_gym/_cbuf.h."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("afvsgp_gym.cbf._cones", ["afvsgp_gym/cbf/_cones.c"], optional=True,
                  depends=["afvsgp_gym/_cbuf.h"], extra_compile_args=["-O2"]),
        Extension("afvsgp_gym.cbf._step", ["afvsgp_gym/cbf/_step.c"], optional=True,
                  depends=["afvsgp_gym/_cbuf.h"], extra_compile_args=["-O2", "-ffp-contract=off"]),
        Extension("afvsgp_gym.gp._bank", ["afvsgp_gym/gp/_bank.c"], optional=True,
                  depends=["afvsgp_gym/_cbuf.h", "afvsgp_gym/gp/_bank_simd.h"],
                  extra_compile_args=["-O3", "-ffp-contract=off"]),
        Extension("afvsgp_gym.robots._arm", ["afvsgp_gym/robots/_arm.c"], optional=True,
                  depends=["afvsgp_gym/_cbuf.h"], extra_compile_args=["-O2"]),
    ],
)
