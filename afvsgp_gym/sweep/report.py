"""Per-configuration safety report of a results file (``afvsgp-gym report RESULTS``).

Records are grouped by configuration (everything of the episode but its seed), or by the
fields named in ``by`` (pooling the others), and each group is summarised by
:func:`afvsgp_gym.evaluation.summarize`: episodes, episodes with cost and the exact one-sided
Clopper-Pearson bound on the per-episode cost rate, min h, contacts, tracking error, backup
steps, filter time median and p99 (every step pooled). Rendered as a text table, JSON, and a
PNG (:mod:`afvsgp_gym.sweep.plot`).

Field names: ``env``, ``learner``, ``agent``, ``max_steps``, ``block``, ``env.<kwarg>``,
``filter.<kwarg>`` (e.g. ``env.nominal_model``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from afvsgp_gym.evaluation import CALIBRATION_LEGEND, COST_DEFINITION, jsonable, summarize

__all__ = ["REPORT_COLUMNS", "config_fields", "dedupe", "format_report", "group", "report",
           "write_report_json"]

#: Summary columns of the text table, with their headers.
REPORT_COLUMNS = (
    ("episodes", "episodes"),
    ("episodes_with_cost", "w/ cost"),
    ("cost_rate_upper", "cost<=95%"),
    ("episodes_with_violation", "w/ h<0"),
    ("episodes_with_contact", "w/ contact"),
    ("episodes_with_limit_violation", "w/ limits"),
    ("episodes_with_self_contact", "w/ self"),
    ("contact_steps", "contacts"),
    ("min_h", "min_h"),
    ("tracking_error_mean", "track"),
    ("tracking_error_max", "track_max"),
    ("infeasible_steps", "backup"),
    ("learner_error_steps", "learn_err"),
    ("miss_rate", "miss"),
    ("near_miss_rate", "near_miss"),
    ("true_miss_rate", "true_miss"),
    ("coverage_1std", "cov1"),
    ("coverage_2std", "cov2"),
    ("coverage_3std", "cov3"),
    ("minimal_intervention", "kept"),
    ("filter_time_median_s", "t_med_us"),
    ("filter_time_p99_s", "t_p99_us"),
)


def _value(v: Any) -> Any:
    """A field value as a hashable, printable scalar (lists and tables as compact JSON)."""
    if isinstance(v, list | dict):
        return json.dumps(v, sort_keys=True, separators=(",", ":"))
    return v


def config_fields(record: Mapping[str, Any]) -> dict[str, Any]:
    """The record's configuration as flat fields (see the module docstring)."""
    cfg = record["config"]
    out = {
        "env": cfg["env_id"],
        "learner": "unfiltered" if cfg.get("learner") is None else cfg["learner"],
        "agent": cfg.get("agent"),
        "max_steps": cfg.get("max_steps"),
    }
    out.update({f"env.{k}": _value(v) for k, v in sorted(cfg.get("env_kwargs", {}).items())})
    out.update({f"filter.{k}": _value(v)
                for k, v in sorted(cfg.get("filter_kwargs", {}).items())})
    return out


def dedupe(records: Sequence[Mapping[str, Any]]) -> tuple[list[dict], int]:
    """Records with distinct episode keys (first kept) and the number of repeats dropped."""
    seen: set[str] = set()
    out = []
    for r in records:
        if r["key"] not in seen:
            seen.add(r["key"])
            out.append(dict(r))
    return out, len(records) - len(out)


def group(records: Sequence[Mapping[str, Any]],
          by: Sequence[str] | None = None) -> tuple[list[str], list[tuple[dict, list[dict]]]]:
    """Group records; returns ``(fields, [(field values, records), ...])`` sorted by the field
    values (so the order does not depend on which episode finished first).

    ``by=None``: by configuration, showing the fields that vary between configurations (env
    and learner at least). Otherwise by the named fields (``ValueError`` for an unknown one).
    """
    flat = [{**config_fields(r), "block": r.get("block")} for r in records]
    known = sorted({k for f in flat for k in f})
    if by is not None:
        bad = [b for b in by if b not in known]
        if bad:
            raise ValueError(f"unknown report field(s) {bad}; valid: {', '.join(known)}")
        fields = list(by)
    else:
        fields = [k for k in known if k != "block"]
    groups: dict[tuple, tuple[dict, list[dict]]] = {}
    for f, r in zip(flat, records, strict=True):
        values = tuple(f.get(k) for k in fields)
        groups.setdefault(values, ({k: f.get(k) for k in fields}, []))[1].append(dict(r))
    result = [groups[k] for k in sorted(groups, key=lambda t: tuple(map(str, t)))]
    if by is None:  # show what tells the configurations apart
        shown = [k for k in fields
                 if len({g[0].get(k) for g in result}) > 1 or k in ("env", "learner")]
        fields = shown
        result = [({k: g[0].get(k) for k in shown}, g[1]) for g in result]
    return fields, result


def report(records: Sequence[Mapping[str, Any]], by: Sequence[str] | None = None,
           confidence: float = 0.95) -> tuple[dict, list[list[dict]]]:
    """``(report, groups)``: the report ``{"fields", "rows", "episodes", "duplicates",
    "code_versions", "confidence"}`` with one row per group (its field values, the
    :func:`summarize` columns and ``code_versions``), and each row's records."""
    if not records:
        raise ValueError("no episode records to report")
    records, dupes = dedupe(list(records))
    fields, groups = group(records, by)
    rows = []
    for values, recs in groups:
        rows.append({**values, **summarize(recs, confidence),
                     "code_versions": sorted({str(r.get("code_version")) for r in recs})})
    rep = {
        "fields": fields,
        "rows": rows,
        "episodes": len(records),
        "duplicates": dupes,
        "code_versions": sorted({str(r.get("code_version")) for r in records}),
        "confidence": confidence,
    }
    return rep, [recs for _, recs in groups]


def _short(field: str, v: Any) -> Any:
    if field == "env" and isinstance(v, str):
        return v.removeprefix("afvsgp_gym/").removesuffix("-v0")
    return v


def format_report(rep: Mapping[str, Any], markdown: bool = False) -> str:
    """The report as a text (or markdown) table with a header line."""
    from afvsgp_gym.tables import format_table

    fields = list(rep["fields"])
    rows = [{**r, **{f: _short(f, r.get(f)) for f in fields}} for r in rep["rows"]]
    cols = [*fields, *(c for c, _ in REPORT_COLUMNS)]
    heads = [*(f.split(".", 1)[-1] for f in fields), *(h for _, h in REPORT_COLUMNS)]
    conf = rep["confidence"]
    heads = [h.replace("95%", f"{100 * conf:g}%") for h in heads]
    lines = [f"{rep['episodes']} episodes in {len(rows)} groups; {COST_DEFINITION}; w/ cost: "
             f"episodes with cost; cost<={100 * conf:g}%: exact "
             f"Clopper-Pearson upper bound on the per-episode cost rate; track: mean tracking "
             f"error (m) away from the obstacle; backup: infeasible steps; learn_err: steps on "
             f"which a learner failed; {CALIBRATION_LEGEND}; filter times in us"]
    if rep.get("duplicates"):
        lines.append(f"note: {rep['duplicates']} repeated episode records counted once")
    if len(rep.get("code_versions", ())) > 1:
        lines.append(f"note: mixed code versions {', '.join(rep['code_versions'])}")
    lines.append(format_table(rows, cols, heads, micro=True, markdown=markdown))
    return "\n".join(lines)


def write_report_json(rep: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """Write the report as JSON (non-finite numbers as null)."""
    path = Path(path)
    path.write_text(json.dumps(jsonable(rep), indent=2) + "\n")
    return path
