"""Standalone learned HOCBF safety controller (paper Algorithm 1), no simulator needed.

Example
-------
>>> import numpy as np
>>> from afvsgp_gym.types import BarrierTerms
>>> ctrl = SafetyController(-np.ones(2), np.ones(2), learner="none", alpha=2.0)
>>> terms = [BarrierTerms(np.array([0.1, -0.2]), 0.0, np.array([1.0, 0.0]), np.zeros(3))]
>>> res = ctrl.filter(np.array([-1.0, 0.5]), terms)
>>> res.feasible, bool(res.active), np.round(res.u, 3).tolist()
(True, True, [0.404, 0.5])

In a real robot loop: ``res = ctrl.filter(u_nom, terms, u_backup=brake)``; apply ``res.u`` for
one control period ``dt``; read the new terms; ``ctrl.observe(terms, res.u, new_terms, dt)``.
``u_backup`` (optional) is the action to apply when no action satisfies the chance constraints,
e.g. a joint-damping brake; without it the filter falls back to the action that maximises the
worst predicted margin.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dpotrf

from afvsgp_gym.cbf.hocbf import HOCBF
from afvsgp_gym.cbf.learners import LEARNING, check_learner_name, make_learner
from afvsgp_gym.cbf.measurement import measure
from afvsgp_gym.cbf.socp import SOCPFilter
from afvsgp_gym.types import BarrierTerms

#: Learner settings used unless ``learner_kwargs`` overrides them. AFVSGP: the paper's window
#: P = 200 with phi = 0.99 remembers ~100 samples (0.4 s at the Franka's 250 Hz); with a
#: "zero" nominal model the action gain L_g L_f h is only identifiable from the exploration
#: of the warm-up, and forgetting it within a second of smooth tracking left the model with a
#: wrong gain (and violations) on the dynamic scenario. window 1000, phi = 0.999 keeps it.
DEFAULT_LEARNER_KWARGS: dict[str, dict] = {"afvsgp": {"window": 1000, "forgetting": 0.999}}

#: Default confidence multiplier of the chance constraint. Eq. 49's bound (Castaneda et al.
#: 2021, Thm. 2) is far too conservative to be feasible in practice (it grows with
#: ln^3(P / delta)); like Castaneda et al. we use a constant. beta = 3 (one-sided 99.87 %
#: Gaussian quantile per step) was the best of 2, 2.5, 3, 3.5 on the Franka sweeps with the
#: "zero" nominal model (benchmarks/filter.md): with 2 the learned posterior, which is
#: overconfident away from the data, let 1-6 of 20 Franka episodes violate.
DEFAULT_BETA = 3.0

#: Default weight of the residual correction (an exponential average over ~1/0.2 = 5 steps of
#: the measured minus the predicted ``Delta B^(r)``). Without it a model that is confidently
#: wrong (3-10 predicted standard deviations, same sign for tens of steps) let the arm creep
#: into the obstacle while every SOCP was "Solved" (benchmarks/filter.md).
DEFAULT_RESIDUAL_CORRECTION = 0.2


@dataclass(frozen=True)
class FilterResult:
    """One filtered action.

    Attributes
    ----------
    u : ndarray of shape (m,)
        Safe action, finite and inside the bounds.
    feasible : bool
        False when the fallback (max worst margin) was used.
    active : bool
        True when the filter changed the (clipped) proposed action, or fell back.
    status : str
        ``"inactive"``, the solver status, ``"backup:..."`` (infeasible: the backup action),
        ``"fallback:..."`` (infeasible: max worst margin) or ``"invalid_input"``.
    margins : ndarray of shape (K,)
        Chance-constraint margins at ``u``.
    delta_b_mean, delta_b_std : ndarray of shape (K,)
        Learned mean and standard deviation of ``Delta B^(r)`` at ``u`` (eq. 51).
    solve_time_s : float
        Wall time of prediction and cone program.
    warmup : bool
        True while Algorithm 1's warm-up collects its first samples (nominal-only filter plus
        exploration noise).
    """

    u: np.ndarray
    feasible: bool
    active: bool
    status: str
    margins: np.ndarray
    delta_b_mean: np.ndarray
    delta_b_std: np.ndarray
    solve_time_s: float
    warmup: bool = False


def _cone_matrix(sigma: np.ndarray, beta: float) -> np.ndarray:
    """``G = beta L'`` with ``Sigma = L L'`` (eq. 05 with the standard deviation, eq. 51):
    ``||G ubar|| = beta sqrt(ubar' Sigma ubar)``. The Cholesky factor (LAPACK ``potrf``,
    ``L' = U`` upper) when Sigma is numerically positive definite, else the eigen-factor
    ``diag(sqrt(max(w, 0))) V'`` (singular or rounding-level indefinite Sigma)."""
    sym = 0.5 * (sigma + sigma.T)
    upper, info = dpotrf(sym, lower=0, clean=1)
    if info == 0:
        upper *= beta
        return upper
    w, v = np.linalg.eigh(sym)
    return (beta * np.sqrt(np.maximum(w, 0.0)))[:, None] * v.T


class SafetyController:
    """Learned HOCBF safety filter: chance-constrained SOCP + one learner per obstacle.

    Parameters
    ----------
    action_low, action_high : array_like of shape (m,)
        Action bounds (the filter never leaves them).
    n_obstacles : int
        Number of barriers; one learner and one cone each.
    relative_degree : int
        Relative degree ``r`` of every barrier (2 for the provided envs).
    learner : str
        One of :data:`afvsgp_gym.cbf.LEARNERS`.
    alpha : float or sequence of float
        Linear class-K gains ``a_1..a_r`` of the HOCBF chain (default 4.0).
    beta : float
        Chance-constraint multiplier on the predicted standard deviation (eq. 49; default
        :data:`DEFAULT_BETA`). ``beta = 0`` gives the mean-only QP.
    barrier_margin : float
        Buffer subtracted from ``h`` in the constraint (units of ``h``; 1 mm for the provided
        envs): the HOCBF condition holds in continuous time, and with a zero-order-hold action
        over ``dt`` the sampled ``h`` can dip O(dt^2) below the boundary without it.
    warmup_samples : int
        ``P``: samples collected before the offline hyperparameter fit (Algorithm 1; 200).
    exploration_noise : float
        Std of the Gaussian noise added to the action during warm-up, as a fraction of the
        half range of the bounds (default 0.3).
    online_exploration : float
        Std of the noise added to the proposed action after warm-up (same units as
        ``exploration_noise``; default 0.05). Persistent excitation: with a "zero" nominal model
        the action gain is only identifiable along directions the actions have explored. The
        noisy proposal is then filtered, so the constraint still holds.
    residual_correction : float
        Weight ``w`` in [0, 1) of the residual correction, a disturbance observer on top of the
        learner: after every step the measured ``z`` (eq. 48) is compared with the learned mean
        the filter used, ``e = z - b' ubar``, and ``bias <- (1 - w) bias + w e`` (one per
        obstacle, ``residual_bias``) is added to the mean in the next constraints (eq. 05).
        A learner that is wrong in a persistent direction (the drift or the action gain changed
        faster than the posterior adapts) is thereby corrected within ~1/w steps; zero-mean
        errors average out. Default :data:`DEFAULT_RESIDUAL_CORRECTION`; 0 disables it. Only
        for learning learners, after warm-up.
    calibration_rate : float
        Online variance calibration: every observed ``z`` is compared with the prediction the
        filter used for that step, and an exponential average (rate ``calibration_rate``) of
        ``(z - mean)^2 / (var + max(noise, 0.01 var(z_warmup)))`` scales the covariance in
        the cone when it exceeds 1 (``variance_scale``, one per obstacle): an overconfident
        model becomes more cautious within ~1/rate steps. Default 0 (off): at 0.02 it removed
        the remaining Franka violations but made the filter so cautious that the arm stopped
        tracking (mean error 0.35-0.47 m away from the obstacle on 3 of 4 episodes).
    learner_kwargs : dict or None
        Passed to the learner's constructor, on top of :data:`DEFAULT_LEARNER_KWARGS`.
    learn_hyperparameters : bool
        Maximise the bound at the end of warm-up (True) or keep the given kernel.
    kernel_init : {"uniform", "data"} or float
        Initial ADP kernel for the offline fit when ``learner_kwargs`` has no ``kernel``:
        ``"data"`` is the learner's heuristic (per-feature ``sqrt(b) std``, which makes features
        that barely move during warm-up extremely short-scaled, so the model cannot extrapolate
        when they move later); ``"uniform"`` (default) uses the largest of those lengthscales for
        every feature; a float sets every lengthscale. Variances follow ``ADPKernel.from_data``.
    noise_floor : float
        Lower bound on the learned noise variance, relative to ``var(z)`` of the warm-up data.
        Eq. 48's samples are nearly noise-free, so maximising the bound drives the noise to
        ~1e-6 var(z) and the posterior becomes overconfident away from the data (violations
        with a "Solved" SOCP); below the floor the fitted kernel is kept and the posterior is
        recomputed with the floor. 0 (default) disables it: a floor of 0.01 made the filter
        fall back more often and violate more on the dynamic Franka scenario.
    dataset : tuple or list of tuples or None
        ``(xi (N, b), u (N, m), z (N,))`` recorded beforehand (one tuple for every obstacle,
        or one per obstacle): the learners are fitted at construction and warm-up is skipped.
    online : bool
        Update the learners with every observed sample after warm-up (``learning``).
    qp_solver : str or None
        qpsolvers backend for the plain-QP case (None: clarabel directly).
    seed : int or None
        Seed of the exploration noise.
    """

    def __init__(
        self,
        action_low,
        action_high,
        n_obstacles: int = 1,
        relative_degree: int = 2,
        learner: str = "afvsgp",
        *,
        alpha: float | Sequence[float] = 4.0,
        beta: float = DEFAULT_BETA,
        barrier_margin: float = 1e-3,
        warmup_samples: int = 200,
        exploration_noise: float = 0.3,
        online_exploration: float = 0.05,
        residual_correction: float = DEFAULT_RESIDUAL_CORRECTION,
        calibration_rate: float = 0.0,
        learner_kwargs: dict | None = None,
        learn_hyperparameters: bool = True,
        kernel_init: str | float = "uniform",
        noise_floor: float = 0.0,
        dataset=None,
        online: bool = True,
        qp_solver: str | None = None,
        seed: int | None = None,
    ):
        self.learner_name = check_learner_name(learner)
        if not isinstance(n_obstacles, (int, np.integer)) or n_obstacles < 1:
            raise ValueError(f"n_obstacles must be a positive integer. Got: {n_obstacles!r}")
        if not (np.isfinite(barrier_margin) and barrier_margin >= 0):
            raise ValueError(f"barrier_margin must be finite and >= 0. Got: {barrier_margin!r}")
        if not (np.isfinite(beta) and beta >= 0):
            raise ValueError(f"beta must be finite and >= 0. Got: {beta!r}")
        if not isinstance(warmup_samples, (int, np.integer)) or warmup_samples < 2:
            raise ValueError(f"warmup_samples must be an integer >= 2. Got: {warmup_samples!r}")
        if not (
            kernel_init in ("uniform", "data")
            or (
                isinstance(kernel_init, (int, float))
                and np.isfinite(kernel_init)
                and kernel_init > 0
            )
        ):
            raise ValueError(
                f"kernel_init must be 'uniform', 'data' or a positive float. Got: {kernel_init!r}"
            )
        if not (np.isfinite(noise_floor) and noise_floor >= 0):
            raise ValueError(f"noise_floor must be finite and >= 0. Got: {noise_floor!r}")
        if not (np.isfinite(exploration_noise) and exploration_noise >= 0):
            raise ValueError(f"exploration_noise must be >= 0. Got: {exploration_noise!r}")
        if not (np.isfinite(residual_correction) and 0 <= residual_correction < 1):
            raise ValueError(
                f"residual_correction must be in [0, 1). Got: {residual_correction!r}"
            )
        if not (np.isfinite(calibration_rate) and 0 <= calibration_rate <= 1):
            raise ValueError(f"calibration_rate must be in [0, 1]. Got: {calibration_rate!r}")
        if not (np.isfinite(online_exploration) and online_exploration >= 0):
            raise ValueError(f"online_exploration must be >= 0. Got: {online_exploration!r}")
        self.hocbf = HOCBF(relative_degree, alpha)
        self._margin_gain = float(np.prod(self.hocbf.gains))  # d psi_r / d h
        self.socp = SOCPFilter(action_low, action_high, n_obstacles, qp_solver=qp_solver)
        self.low, self.high = self.socp.low, self.socp.high
        self._half_range = 0.5 * (self.high - self.low)
        self.action_dim = self.socp.m
        self.n_obstacles = int(n_obstacles)
        self.relative_degree = int(relative_degree)
        self.beta = float(beta)
        self.barrier_margin = float(barrier_margin)
        self.warmup_samples = int(warmup_samples)
        self.exploration_noise = float(exploration_noise)
        self.online_exploration = float(online_exploration)
        self.residual_correction = float(residual_correction)
        self.residual_bias = np.zeros(int(n_obstacles))
        self.calibration_rate = float(calibration_rate)
        self.variance_scale = np.ones(int(n_obstacles))
        self._last_pred: list | None = None
        self._z_floor = np.zeros(int(n_obstacles))
        self.learn_hyperparameters = bool(learn_hyperparameters)
        self.kernel_init = kernel_init
        self.noise_floor = float(noise_floor)
        self.learning = bool(online)
        self._learner_kwargs = {
            **DEFAULT_LEARNER_KWARGS.get(self.learner_name, {}),
            **(learner_kwargs or {}),
        }
        self.learners = [
            make_learner(self.learner_name, self.action_dim, **self._learner_kwargs)
            for _ in range(self.n_obstacles)
        ]
        self._rng = np.random.default_rng(seed)
        self._buffer: list[list[tuple[np.ndarray, np.ndarray, float]]] = [
            [] for _ in range(self.n_obstacles)
        ]
        self.fitted = self.learner_name not in LEARNING
        self.n_update_failures = 0
        self.n_skipped_samples = 0
        self.last_error: str | None = None
        if dataset is not None and self.learner_name in LEARNING:
            self.fit(dataset)

    # ------------------------------------------------------------------ state
    def reset_residuals(self) -> None:
        """Forget the residual correction (e.g. at an episode reset: the state jumps)."""
        self.residual_bias[:] = 0.0
        self._last_pred = None

    @property
    def warming_up(self) -> bool:
        """True until the learners are fitted (Algorithm 1 warm-up)."""
        return not self.fitted

    def dataset(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Warm-up samples collected so far, one ``(xi, u, z)`` tuple per obstacle."""
        out = []
        for buf in self._buffer:
            if buf:
                xi, u, z = zip(*buf, strict=True)
                out.append((np.array(xi), np.array(u), np.array(z)))
            else:
                out.append((np.zeros((0, 0)), np.zeros((0, self.action_dim)), np.zeros(0)))
        return out

    def fit(self, dataset) -> SafetyController:
        """Fit every learner offline on ``dataset`` (one tuple, or one per obstacle)."""
        if isinstance(dataset, tuple):
            dataset = [dataset] * self.n_obstacles
        if len(dataset) != self.n_obstacles:
            raise ValueError(
                f"dataset must hold one (xi, u, z) tuple or {self.n_obstacles}. Got: {len(dataset)}"
            )
        for k, (xi, u, z) in enumerate(dataset):
            xi = np.asarray(xi, np.float64)
            u = np.asarray(u, np.float64).reshape(len(xi), self.action_dim)
            z = np.asarray(z, np.float64).ravel()
            ok = np.all(np.isfinite(xi), axis=1) & np.all(np.isfinite(u), axis=1)
            ok &= np.isfinite(z)
            xi, u, z = xi[ok], u[ok], z[ok]
            self.learners[k] = self._fit_one(xi, u, z)
            self._z_floor[k] = 0.01 * (float(np.var(z)) if len(z) > 1 else 1.0)
        self.fitted = True
        return self

    def _fit_one(self, xi, u, z):
        learner = self._fit_restarts(xi, u, z)
        floor = self.noise_floor * (float(np.var(z)) if len(z) > 1 else 1.0)
        noise = getattr(learner, "noise_variance_", None)
        kernel = getattr(learner, "kernel_", None)
        if (
            self.learn_hyperparameters
            and kernel is not None
            and noise is not None
            and noise < floor
        ):
            kwargs = {**self._learner_kwargs, "kernel": kernel, "noise_variance": floor}
            learner = make_learner(self.learner_name, self.action_dim, **kwargs)
            learner.fit(xi, u, z, learn_hyperparameters=False)
        return learner

    def _fit_restarts(self, xi, u, z):
        """Fit one learner; restart from other initial points if the optimiser did not move.

        L-BFGS-B on the collapsed bound sometimes stops at its initial point (a failed line
        search: the first step lands where the Cholesky fails); the restarts are a smaller
        initial noise variance, doubled lengthscales and the learner's own data heuristic.
        """
        user_kernel = "kernel" in self._learner_kwargs
        if not self.learn_hyperparameters or user_kernel or self.kernel_init == "data":
            starts = [{}]
        else:
            k0 = self._initial_kernel(xi, u, z)
            vz = float(np.var(z)) if len(z) > 1 else 1.0
            starts = [
                {"kernel": k0},
                {"kernel": k0, "noise_variance": max(0.01 * vz, 1e-8)},
                {"kernel": type(k0)(2.0 * k0.lengthscales, k0.variances)},
                {"kernel": None},
            ]
        best, best_bound = None, -np.inf
        for start in starts:
            kwargs = {**self._learner_kwargs, **start}
            learner = make_learner(self.learner_name, self.action_dim, **kwargs)
            learner.fit(xi, u, z, learn_hyperparameters=self.learn_hyperparameters)
            if len(starts) == 1:
                return learner
            k0 = start.get("kernel")
            fitted_kernel = getattr(learner, "kernel_", None)
            moved = (
                k0 is None
                or fitted_kernel is None
                or not np.allclose(fitted_kernel.theta, k0.theta)
            )
            bound = float(getattr(learner, "bound_", None) or 0.0)
            if moved:
                return learner
            if best is None or bound > best_bound:
                best, best_bound = learner, bound
        return best

    def _initial_kernel(self, xi, u, z):
        from afvsgp_gym.gp import ADPKernel

        base = ADPKernel.from_data(xi, u, z)
        m1, b = self.action_dim + 1, xi.shape[1]
        if self.kernel_init == "uniform":
            std = xi.std(axis=0) if len(xi) > 1 else np.ones(b)
            ls = float(np.sqrt(b) * np.max(std)) if np.max(std) > 1e-12 else 1.0
        else:
            ls = float(self.kernel_init)
        return ADPKernel(np.full((m1, b), ls), base.variances)

    # ------------------------------------------------------------------ filter
    def _terms_ok(self, terms: Sequence[BarrierTerms]) -> np.ndarray:
        ok = np.ones(self.n_obstacles, dtype=bool)
        total = 0.0
        try:  # one sum per term: finite unless a NaN/inf is present (or overflow)
            for t in terms:
                total += float(t.lf) + float(t.derivatives.sum() + t.lg.sum() + t.xi.sum())
        except (AttributeError, TypeError):
            total = np.nan
        if math.isfinite(total):
            return ok
        for k, t in enumerate(terms):
            ok[k] = bool(
                np.all(np.isfinite(t.derivatives))
                and np.isfinite(t.lf)
                and np.all(np.isfinite(t.lg))
                and np.all(np.isfinite(t.xi))
            )
        return ok

    def filter(
        self,
        u_nom,
        terms: Sequence[BarrierTerms],
        true_terms: Sequence[BarrierTerms] | None = None,
        u_backup=None,
    ) -> FilterResult:
        """Project ``u_nom`` onto the (chance-)constrained safe set (eq. 05).

        ``terms`` are the nominal barrier terms (one per obstacle); the oracle learner uses
        ``true_terms`` instead. ``u_backup`` (array of shape (m,) or a zero-argument callable
        returning one, evaluated only when needed) is applied, clipped to the bounds, when
        the program is infeasible or fails (status ``"backup:..."``); without it, or if it is
        not finite, the action maximising the worst margin is used (``"fallback:..."``).
        Never raises for NaN values: they give the flagged fallback.
        """
        t0 = time.perf_counter()
        K, m = self.n_obstacles, self.action_dim
        if len(terms) != K:
            raise ValueError(f"terms must hold {K} BarrierTerms. Got: {len(terms)}")
        if self.learner_name == "oracle":
            if true_terms is None:
                raise ValueError("learner 'oracle' needs true_terms")
            if len(true_terms) != K:
                raise ValueError(f"true_terms must hold {K} BarrierTerms. Got: {len(true_terms)}")
            terms = true_terms
        u_nom = np.array(u_nom, dtype=np.float64).ravel()  # a copy
        if u_nom.shape != (m,):
            raise ValueError(f"u_nom must have shape ({m},). Got: {u_nom.shape}")
        warm = self.warming_up
        noise = self.exploration_noise if warm else self.online_exploration
        if self.learner_name not in LEARNING:
            noise = 0.0
        nom_finite = math.isfinite(float(u_nom.sum())) or bool(np.all(np.isfinite(u_nom)))
        if noise > 0 and nom_finite:
            u_nom = u_nom + noise * self._half_range * self._rng.standard_normal(m)
        u_clip = np.clip(u_nom, self.low, self.high)  # what the SOCP clips to (identical)
        if noise > 0 and nom_finite:
            u_nom = u_clip

        ok = self._terms_ok(terms)
        a0 = np.full(K, np.nan)
        a = np.full((K, m), np.nan)
        bs = np.zeros((K, m + 1))
        G = np.zeros((K, m + 1, m + 1))
        sig = np.zeros((K, m + 1, m + 1))
        betas = np.zeros(K)  # cone multiplier per obstacle (0: no cone)
        use_cone = False
        for k, t in enumerate(terms):
            if not ok[k]:
                continue
            try:
                c0, c = self.hocbf.constraint(t)
                c0 -= self.barrier_margin * self._margin_gain
                a0[k], a[k] = c0, c
                if not warm and self.learner_name in LEARNING:
                    b, s = self.learners[k].predict_affine(np.asarray(t.xi, np.float64)[None])
                    bs[k], sig[k] = b[0], s[0]
                    a0[k] += b[0, 0] + self.residual_bias[k]
                    a[k] += b[0, 1:]
                    if self.beta > 0:
                        scale = max(1.0, float(self.variance_scale[k]))
                        betas[k] = self.beta * math.sqrt(scale)
            except ValueError:
                raise
            except Exception as exc:  # a learner failure must not stop the loop
                self.last_error = f"{type(exc).__name__}: {exc}"
                a0[k] = np.nan
        for k in np.flatnonzero(betas):  # factor the covariances
            try:
                G[k] = _cone_matrix(sig[k], betas[k])
                use_cone = True
            except Exception as exc:
                self.last_error = f"{type(exc).__name__}: {exc}"
                a0[k] = np.nan
        # solve returns the clipped proposal at once (status "inactive") when it satisfies
        # every chance constraint: it is then the SOCP optimum itself
        res = self.socp.solve(u_nom, a0, a, G if use_cone else None, u_backup)
        u = res.u
        ubar = np.empty(m + 1)
        ubar[0] = 1.0
        ubar[1:] = u
        self._last_pred = None if warm else (bs, sig, u.copy())
        mean = bs @ ubar
        std = np.sqrt(np.maximum(((sig @ ubar) * ubar).sum(axis=1), 0.0))
        return FilterResult(
            u=u,
            feasible=res.feasible,
            active=res.status != "inactive",
            status=res.status,
            margins=res.margins,
            delta_b_mean=mean,
            delta_b_std=std,
            solve_time_s=time.perf_counter() - t0,
            warmup=warm,
        )

    # ------------------------------------------------------------------ learning
    def _update_residuals(self, samples, u) -> None:
        """Residual correction (``residual_correction``) from the prediction used for the
        step just taken, then the variance calibration (``calibration_rate``)."""
        pred, self._last_pred = self._last_pred, None
        if pred is None:
            return
        d = pred[2] - u  # the applied action may be a float32 copy of the filtered one
        if not float(d @ d) <= 1e-12 * (1.0 + float(u @ u)):
            return
        w = self.residual_correction
        if w > 0:
            ubar = np.concatenate([[1.0], u])
            for k, s in enumerate(samples):
                if s is None:
                    continue
                e = s[2] - float(pred[0][k] @ ubar)
                if math.isfinite(e):
                    self.residual_bias[k] += w * (e - self.residual_bias[k])
        if self.calibration_rate > 0:
            self._calibrate(pred, samples, u)

    def _calibrate(self, pred, samples, u) -> None:
        """Update ``variance_scale`` from the prediction ``pred`` used for the step just taken."""
        ubar = np.concatenate([[1.0], u])
        for k, s in enumerate(samples):
            if s is None:
                continue
            noise = float(getattr(self.learners[k], "noise_variance_", 0.0) or 0.0)
            var = float(ubar @ pred[1][k] @ ubar) + max(noise, self._z_floor[k])
            if not var > 0:
                continue
            r = (s[2] - float(pred[0][k] @ ubar)) ** 2 / var
            if np.isfinite(r):
                lam = self.calibration_rate
                self.variance_scale[k] = (1 - lam) * self.variance_scale[k] + lam * min(r, 1e6)

    def observe(
        self,
        terms_before: Sequence[BarrierTerms],
        u_applied,
        terms_after: Sequence[BarrierTerms],
        dt: float,
    ) -> np.ndarray:
        """Build the eq. 48 samples for the step just taken and update the learners.

        Returns the measurements ``z`` (K,) (NaN where skipped). Never raises for NaN data
        (such samples are skipped and counted in ``n_skipped_samples``).
        """
        K = self.n_obstacles
        z_all = np.full(K, np.nan)
        if self.learner_name not in LEARNING:
            return z_all
        if len(terms_before) != K or len(terms_after) != K:
            raise ValueError(f"terms_before and terms_after must hold {K} BarrierTerms")
        u = np.asarray(u_applied, dtype=np.float64).ravel()
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and positive. Got: {dt!r}")
        samples = []
        for k in range(K):
            try:
                xi, z = measure(terms_before[k], u, terms_after[k], dt)
            except Exception:
                xi, z = None, np.nan
            if xi is None or not (np.isfinite(z) and np.all(np.isfinite(xi))):
                self.n_skipped_samples += 1
                samples.append(None)
                continue
            z_all[k] = z
            samples.append((xi, u.copy(), float(z)))
        if not np.all(np.isfinite(u)):
            return z_all
        if self.warming_up:
            for k, s in enumerate(samples):
                if s is not None:
                    self._buffer[k].append(s)
            if min(len(b) for b in self._buffer) >= self.warmup_samples:
                try:
                    self.fit(self.dataset())
                except Exception as exc:
                    self.n_update_failures += 1
                    self.last_error = f"{type(exc).__name__}: {exc}"
                    for b in self._buffer:  # keep the newest half and retry later
                        del b[: len(b) // 2]
            return z_all
        self._update_residuals(samples, u)
        if not self.learning:
            return z_all
        for k, s in enumerate(samples):
            if s is None:
                continue
            try:
                self.learners[k].update(s[0], s[1], s[2])
            except Exception as exc:
                self.n_update_failures += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
        return z_all
