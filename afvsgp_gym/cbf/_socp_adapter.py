"""Temporary: SOCPFilter with a variable number of constraints per call (one per count)."""

from __future__ import annotations

import numpy as np

from afvsgp_gym.cbf.socp import SOCPFilter, SOCPResult


class VariableSOCP:
    def __init__(self, low, high, qp_solver=None):
        self._args = (low, high)
        self._qp = qp_solver
        self._by_k: dict[int, SOCPFilter] = {}
        f = self._get(1)
        self.low, self.high, self.m = f.low, f.high, f.m

    def _get(self, k: int) -> SOCPFilter:
        f = self._by_k.get(k)
        if f is None:
            f = self._by_k[k] = SOCPFilter(*self._args, k, qp_solver=self._qp)
        return f

    def solve(self, u_nom, a0, a, G=None, backup=None) -> SOCPResult:
        k = len(a0)
        if k == 0:
            u = np.clip(np.nan_to_num(u_nom), self.low, self.high)
            if not np.all(np.isfinite(u_nom)):
                centre = np.clip(np.zeros(self.m), self.low, self.high)
                return SOCPResult(centre, False, "invalid_input", np.zeros(0), 0.0)
            return SOCPResult(u, True, "inactive", np.zeros(0), 0.0)
        return self._get(k).solve(u_nom, a0, a, G, backup)
