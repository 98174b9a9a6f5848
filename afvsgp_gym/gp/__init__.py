"""afvsgp_gym.gp: ADP compound kernel and the online GP learners (paper sections II-B, III)."""

from afvsgp_gym.gp.kernels import ADPKernel

__all__ = ["ADPKernel"]
