"""Independent references for the filter's cone program (scipy SLSQP), shared by the solver
tests."""

import numpy as np
from scipy.optimize import minimize


def margins(u, a0, a, G):
    ubar = np.concatenate([[1.0], u])
    out = a0 + a @ u
    return out if G is None else out - np.linalg.norm(G @ ubar, axis=-1)


def slsqp(u_nom, a0, a, G, low, high):
    """Independent reference: SLSQP from two starts, the best feasible answer (every margin
    >= -1e-9). SLSQP can stop a few 1e-8 outside the feasible set (its line search stalls
    at the boundary; on some BLAS it does for these instances), so a start whose answer is
    not feasible is solved again with the constraints tightened by 1e-8, then 1e-7: an
    answer of the tightened program is feasible, and exceeds the optimum by at most the
    multipliers times the tightening (well inside the comparisons' 1e-7)."""
    best = None
    for x0 in [np.clip(u_nom, low, high), 0.5 * (low + high)]:
        for shift in (0.0, 1e-8, 1e-7):
            cons = [
                {
                    "type": "ineq",
                    "fun": lambda u, k=k, s=shift: margins(
                        u, a0[k : k + 1], a[k : k + 1], None if G is None else G[k : k + 1]
                    )[0] - s,
                }
                for k in range(len(a0))
            ]
            r = minimize(
                lambda u: 0.5 * np.sum((u - u_nom) ** 2),
                x0,
                jac=lambda u: u - u_nom,
                bounds=list(zip(low, high, strict=True)),
                constraints=cons,
                method="SLSQP",
                options={"ftol": 1e-15, "maxiter": 1000},
            )
            if np.all(margins(r.x, a0, a, G) >= -1e-9) and np.all(r.x >= low - 1e-12):
                if best is None or r.fun < best.fun:
                    best = r
                break
    return best
