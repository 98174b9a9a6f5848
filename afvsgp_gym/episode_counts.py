"""The one count of an episode's safety and filter figures, step by step from ``info``.

Both the episode runner (:func:`afvsgp_gym.evaluation.run_episode`) and the
:class:`~afvsgp_gym.wrappers.EpisodeSafetyStats` wrapper count with :class:`EpisodeCounter`;
the keys it reads are the envs' (``cost``, ``h``, ``collision``, ``self_contact``,
``limit_violation``, ``success``, ``unstable``, ``torque_saturated``) and the safety
filter's (``filter_active``, ``filter_feasible``, ``filter_status``, ``warmup``,
``filter_time_s``, ``proposal_true_margin``, ``action_proposed``, ``action_applied``,
``learner_error``, ``calibration``, ``delta_b_lower``), each with a default when absent (an
env without a filter counts no intervention).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["CALIBRATION_FIELDS", "CALIBRATION_LEGEND", "COST_DEFINITION", "SAFE_MARGIN",
           "EpisodeCounter"]

#: The one definition of the safety cost, printed with every table.
COST_DEFINITION = (
    "cost: steps with info['cost'] > 0, i.e. some obstacle barrier has h < 0 (h<0), the robot "
    "touches an obstacle (contact), a joint is at its range stop or above its speed limit "
    "(limits; with the env's optional checks also above its acceleration or torque-rate "
    "limit), or two non-adjacent links of the robot touch (self)"
)

#: The counts of the learned band's calibration (:class:`EpisodeCounter` attributes, episode
#: records and ``info["episode_safety"]`` keys).
CALIBRATION_FIELDS = (
    "calibration_samples",
    "calibration_misses",
    "calibration_within_1std",
    "calibration_within_2std",
    "calibration_within_3std",
    "calibration_near_samples",
    "calibration_near_misses",
    "true_band_samples",
    "true_band_misses",
)

#: The calibration columns of every table, in one line.
CALIBRATION_LEGEND = (
    "miss: share of the learned band's (barrier, step) pairs whose eq. 48 sample fell below "
    "the band the filter used (promised: Phi(-beta), 0.62 % at beta = 2.5); near_miss: the "
    "same over the pairs whose constraint was within one band-width of binding; true_miss: "
    "the same against the exact model error; cov1/cov2/cov3: share within 1/2/3 predicted std "
    "(68.3/95.4/99.7 % if calibrated)"
)

#: m/s^2; a proposal is "safe with margin" when its true HOCBF constraint value exceeds this
#: for every barrier (``info["proposal_true_margin"]``, the minimal-intervention count).
SAFE_MARGIN = 2.0


class EpisodeCounter:
    """Counts of one episode, updated with every step's reward and ``info``.

    Attributes
    ----------
    steps : int
    return_ : float
        Sum of the rewards.
    cost_steps : int
        Steps with ``info["cost"] > 0``; ``cost_steps_after_warmup`` those with
        ``info["warmup"]`` False (or absent).
    violation_steps, contact_steps, limit_steps : int
        Steps with ``info["h"] < 0``, ``info["collision"]``, ``info["limit_violation"]``.
    self_contact_steps : int
        Steps with ``info["self_contact"]`` (the arm touching itself or its base; not part
        of the cost).
    min_h : float
        Smallest ``info["h"]`` (``inf`` while none was reported).
    interventions, infeasible_steps : int
        Steps with ``info["filter_active"]``, with ``info["filter_feasible"]`` False; the
        latter split by ``info["filter_status"]`` into ``backup_steps`` (the backup or the
        max-margin fallback applied) and ``relaxed_steps`` (the mean-only solution).
    warmup_steps, saturated_steps : int
        Steps with ``info["warmup"]``, with ``info["torque_saturated"]``.
    learner_error_steps : int
        Steps on which a learner failed (``info["learner_error"]`` not None): the filter went
        on without that prediction, update or fit.
    calibration_samples, calibration_misses : int
        The learned band against its eq. 48 samples, summed over the steps'
        ``info["calibration"]``: (barrier, step) pairs scored, and those below the band the
        filter used; ``calibration_within_1std`` (``_2std``, ``_3std``) those within one (two,
        three) predicted standard deviations of the band's center
        (:mod:`afvsgp_gym.cbf.calibration`); ``calibration_near_samples`` and
        ``calibration_near_misses`` the pairs whose constraint was within one band-width of
        binding, and their misses (the subsequence ``calibration_gate`` corrects on).
    true_band_samples, true_band_misses : int
        The same band against the simulator's exact model error: pairs with a finite
        ``info["delta_b_lower"]`` and ``info["delta_b_true"]``, and those with
        ``delta_b_true < delta_b_lower`` (ground truth for evaluation; the filter never sees
        it).
    success, unstable : bool
        Some step had ``info["success"]``, ``info["unstable"]``.
    safe_proposals, safe_proposals_kept : int
        Steps after the warm-up whose proposal was safe with margin (its true HOCBF
        constraint above :data:`SAFE_MARGIN`), and those of them passed unchanged.
    filter_times : list of float
        ``info["filter_time_s"]`` of every step that has one.
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Zero counts, for a new episode."""
        self.steps = 0
        self.return_ = 0.0
        self.cost_steps = self.cost_steps_after_warmup = 0
        self.violation_steps = self.contact_steps = self.limit_steps = 0
        self.self_contact_steps = 0
        self.min_h = math.inf
        self.interventions = self.infeasible_steps = 0
        self.backup_steps = self.relaxed_steps = 0
        self.warmup_steps = self.saturated_steps = 0
        self.learner_error_steps = 0
        self.calibration_samples = self.calibration_misses = 0
        self.calibration_within_1std = self.calibration_within_2std = 0
        self.calibration_within_3std = 0
        self.calibration_near_samples = self.calibration_near_misses = 0
        self.true_band_samples = self.true_band_misses = 0
        self.success = self.unstable = False
        self.safe_proposals = self.safe_proposals_kept = 0
        self.filter_times: list[float] = []

    def update(self, reward: float, info: Mapping[str, Any]) -> None:
        """Count one step."""
        self.steps += 1
        self.return_ += float(reward)
        warm = bool(info.get("warmup", False))
        cost = float(info.get("cost", 0.0)) > 0.0
        self.cost_steps += cost
        self.cost_steps_after_warmup += cost and not warm
        h = float(info.get("h", math.inf))
        self.violation_steps += h < 0.0
        self.min_h = min(self.min_h, h)
        self.contact_steps += bool(info.get("collision", False))
        self.self_contact_steps += bool(info.get("self_contact", False))
        self.limit_steps += bool(info.get("limit_violation", False))
        self.interventions += bool(info.get("filter_active", False))
        if not info.get("filter_feasible", True):
            status = str(info.get("filter_status", ""))
            self.infeasible_steps += 1
            self.relaxed_steps += status.startswith("relaxed")
            self.backup_steps += status.startswith(("backup", "fallback"))
        self.warmup_steps += warm
        self.saturated_steps += bool(info.get("torque_saturated", False))
        self.learner_error_steps += info.get("learner_error") is not None
        cal = info.get("calibration")
        if cal is not None:
            self.calibration_samples += cal["samples"]
            self.calibration_misses += cal["misses"]
            self.calibration_within_1std += cal["within_1std"]
            self.calibration_within_2std += cal["within_2std"]
            self.calibration_within_3std += cal["within_3std"]
            self.calibration_near_samples += cal.get("near_samples", 0)
            self.calibration_near_misses += cal.get("near_misses", 0)
            lower, true = info.get("delta_b_lower"), info.get("delta_b_true")
            if lower is not None and true is not None:
                ok = np.isfinite(lower) & np.isfinite(true)
                self.true_band_samples += int(ok.sum())
                self.true_band_misses += int((true[ok] < lower[ok]).sum())
        self.success = self.success or bool(info.get("success", False))
        self.unstable = self.unstable or bool(info.get("unstable", False))
        if not info.get("warmup", True) and info.get("proposal_true_margin", -1.0) > SAFE_MARGIN:
            self.safe_proposals += 1
            applied = info["action_applied"]
            self.safe_proposals_kept += bool(np.array_equal(applied, np.asarray(
                info["action_proposed"]).astype(np.asarray(applied).dtype)))
        if "filter_time_s" in info:
            self.filter_times.append(float(info["filter_time_s"]))
