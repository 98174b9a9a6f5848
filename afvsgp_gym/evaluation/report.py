"""An ``evaluate`` result written out: the printed tables, the JSON and the CSV files."""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

from afvsgp_gym.episode_counts import CALIBRATION_LEGEND, COST_DEFINITION
from afvsgp_gym.evaluation.io import jsonable
from afvsgp_gym.evaluation.runner import EPISODE_FIELDS

__all__ = ["format_table", "write_csv", "write_json"]

#: (key, header) of the printed tables; JSON and CSV hold every field.
_EPISODE_TABLE = (("learner", "learner"), ("episode", "ep"), ("seed", "seed"),
                  ("steps", "steps"), ("return", "return"), ("cost_steps", "cost"),
                  ("violation_steps", "h<0"), ("contact_steps", "contact"),
                  ("limit_steps", "limits"), ("min_h", "min_h"),
                  ("interventions", "interv"), ("infeasible_steps", "backup"),
                  ("learner_error_steps", "learn_err"),
                  ("tracking_error_mean", "track"), ("tracking_error_max", "track_max"),
                  ("filter_time_median_s", "t_med_us"), ("filter_time_p99_s", "t_p99_us"))
#: (rate, numerator, denominator) of the episode table's calibration columns
_EPISODE_RATES = (("miss", "calibration_misses", "calibration_samples"),
                  ("near_miss", "calibration_near_misses", "calibration_near_samples"),
                  ("true_miss", "true_band_misses", "true_band_samples"))
_SUMMARY_TABLE = (("learner", "learner"), ("episodes", "episodes"),
                  ("episodes_with_cost", "w/ cost"), ("cost_rate_upper", "cost<=95%"),
                  ("episodes_with_violation", "w/ h<0"), ("episodes_with_contact", "w/ contact"),
                  ("episodes_with_limit_violation", "w/ limits"),
                  ("episodes_with_self_contact", "w/ self"), ("min_h", "min_h"),
                  ("interventions", "interv"), ("infeasible_steps", "backup"),
                  ("learner_error_steps", "learn_err"),
                  ("miss_rate", "miss"), ("near_miss_rate", "near_miss"),
                  ("true_miss_rate", "true_miss"),
                  ("coverage_1std", "cov1"), ("coverage_2std", "cov2"),
                  ("coverage_3std", "cov3"),
                  ("tracking_error_mean", "track"), ("tracking_error_max", "track_max"),
                  ("minimal_intervention", "kept"), ("return_mean", "return"),
                  ("filter_time_median_s", "t_med_us"), ("filter_time_p99_s", "t_p99_us"))


def format_table(result: dict) -> str:
    """Per-episode table followed by the per-learner summary (filter times in microseconds)."""
    from afvsgp_gym.tables import format_table as table

    def cols(spec):
        return [k for k, _ in spec], [h for _, h in spec]

    sum_rows = [{"learner": k, **v} for k, v in result["summary"].items()]
    episodes = [{**r, **{name: (r.get(num, 0) / r[den] if r.get(den) else math.nan)
                         for name, num, den in _EPISODE_RATES}} for r in result["episodes"]]
    spec = (*_EPISODE_TABLE[:-2], *((n, n) for n, _, _ in _EPISODE_RATES), *_EPISODE_TABLE[-2:])
    return ("Episodes\n" + table(episodes, *cols(spec), micro=True)
            + f"\n\nSummary ({COST_DEFINITION}; w/ cost: "
              "episodes with cost; cost<=95%: exact Clopper-Pearson 95 % upper bound on the "
              "per-episode cost rate; track: mean tracking error (m) away from the obstacle; "
              "backup: infeasible steps; learn_err: steps on which a learner failed; "
              f"{CALIBRATION_LEGEND}; kept: share of the proposals safe with margin that "
              "passed unchanged)\n"
            + table(sum_rows, *cols(_SUMMARY_TABLE), micro=True))


def write_json(result: dict, path: str | os.PathLike) -> None:
    """Write ``{"episodes": [...], "summary": {...}}`` (non-finite floats as null)."""
    data = {k: v for k, v in result.items() if k != "traces"}
    Path(path).write_text(json.dumps(jsonable(data), indent=2) + "\n")


def write_csv(result: dict, path: str | os.PathLike) -> None:
    """Write one CSV row per episode with the columns of
    :data:`~afvsgp_gym.evaluation.EPISODE_FIELDS`."""
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(EPISODE_FIELDS))
        w.writeheader()
        for r in result["episodes"]:
            w.writerow({k: r[k] for k in EPISODE_FIELDS})
