"""afvsgp_gym.cbf: HOCBF chain, eq. 48 measurements, chance-constrained SOCP, safety controller.

No Gymnasium or MuJoCo imports: usable in a real robot loop.
"""

from afvsgp_gym.cbf.controller import DEFAULT_BETA, FilterResult, SafetyController
from afvsgp_gym.cbf.hocbf import HOCBF
from afvsgp_gym.cbf.learners import LEARNERS, make_learner
from afvsgp_gym.cbf.measurement import measure
from afvsgp_gym.cbf.socp import SOCPFilter, SOCPResult

__all__ = [
    "DEFAULT_BETA",
    "HOCBF",
    "LEARNERS",
    "FilterResult",
    "SOCPFilter",
    "SOCPResult",
    "SafetyController",
    "make_learner",
    "measure",
]
