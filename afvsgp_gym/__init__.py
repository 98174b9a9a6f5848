"""afvsgp-gym: Franka Panda obstacle-avoidance environments and a learned HOCBF safety filter.

Importing the package registers the Gymnasium ids (string entry points: MuJoCo is only
imported when an environment is made):

- ``afvsgp_gym/FrankaObstacleStatic-v0``
- ``afvsgp_gym/FrankaObstacleDynamic-v0``
- ``afvsgp_gym/FrankaObstacleRandom-v0``
- ``afvsgp_gym/FrankaTabletop-v0``
- ``afvsgp_gym/FrankaShelf-v0``
- ``afvsgp_gym/FrankaObstacleReach-v0``
- ``afvsgp_gym/PointMassObstacle-v0``

``compiled_extensions()`` says which optional C extensions were built
(:mod:`afvsgp_gym._compiled`).
"""

from afvsgp_gym._compiled import available as compiled_extensions
from afvsgp_gym.envs.registration import register_envs

__version__ = "0.1.0"

register_envs()

__all__ = ["__version__", "compiled_extensions", "register_envs"]
