"""Build of the optional compiled core (the rest of the metadata is in pyproject.toml).

``afvsgp_gym.cbf._cones`` (the certified several-cones fast path of the filter's cone program)
is optional: without a C compiler the build goes on and the filter uses its numpy paths."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("afvsgp_gym.cbf._cones", ["afvsgp_gym/cbf/_cones.c"], optional=True,
                  extra_compile_args=["-O2"]),
    ],
)
