"""afvsgp_gym.gp: ADP compound kernel and the online GP learners (paper sections II-B, III)."""

from afvsgp_gym.gp.afvsgp import AFVSGP
from afvsgp_gym.gp.exact import ExactGP
from afvsgp_gym.gp.kernels import ADPKernel
from afvsgp_gym.gp.sogp import SOGP
from afvsgp_gym.gp.vsgp import VSGP

__all__ = ["AFVSGP", "ADPKernel", "ExactGP", "SOGP", "VSGP"]
