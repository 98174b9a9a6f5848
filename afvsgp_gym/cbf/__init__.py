"""afvsgp_gym.cbf: HOCBF chain, eq. 48 measurements, chance-constrained SOCP, safety controller.

No Gymnasium or MuJoCo imports: usable in a real robot loop.
"""

from afvsgp_gym.cbf.config import DEFAULT_BETA, FilterConfig
from afvsgp_gym.cbf.controller import FilterResult, SafetyController, StepPrediction
from afvsgp_gym.cbf.hocbf import HOCBF
from afvsgp_gym.cbf.learners import LEARNERS, REGISTRY, make_bank, make_learner
from afvsgp_gym.cbf.measurement import measure, measure_all
from afvsgp_gym.cbf.socp import SOCPFilter, SOCPResult

__all__ = [
    "DEFAULT_BETA",
    "HOCBF",
    "LEARNERS",
    "REGISTRY",
    "FilterConfig",
    "FilterResult",
    "SOCPFilter",
    "SOCPResult",
    "SafetyController",
    "StepPrediction",
    "make_bank",
    "make_learner",
    "measure",
    "measure_all",
]
