"""The one episode runner: seeded episodes of an agent behind the safety filter, counted.

An episode is an :class:`EpisodeSpec` (env id and kwargs, learner and filter kwargs, agent,
seed, step cap); :func:`run_spec` builds a fresh env and filter, runs it with
:func:`run_episode` and returns a JSON-able record, deterministic given the spec whatever the
process it runs in (the env is reset with the seed and the filter's exploration noise is seeded
with it). ``evaluate`` and ``afvsgp-gym sweep`` both run episodes this way, through the
executors of :mod:`afvsgp_gym.executors` (in-process, a local process pool, or Ray).

Per episode (see :data:`EPISODE_FIELDS`): ``cost_steps`` (``info["cost"] > 0``, see
:data:`COST_DEFINITION`), and by kind ``violation_steps`` (``info["h"] < 0``), ``contact_steps``
(``info["collision"]``), ``limit_steps`` (``info["limit_violation"]``),
``self_contact_steps`` (``info["self_contact"]``: the arm touching itself, not part of the
cost yet), ``min_h``,
``interventions`` (``info["filter_active"]``),
``infeasible_steps`` (``not info["filter_feasible"]``: the filter applied its backup),
``learner_error_steps`` (``info["learner_error"]``: a learner failed, the filter went on),
``tracking_error_mean``/``_max`` over the steps after the env's warm-up whose reference keeps
``info["reference_h"] >= REFERENCE_CLEARANCE`` from every obstacle (NaN when no step does or
the env reports neither), filter time median and 99th percentile. The headline safety number
of a set of episodes is the number of episodes with cost, with its Clopper-Pearson bound
(:func:`summarize`).

One module per job:

- :mod:`~afvsgp_gym.evaluation.spec`: :class:`EpisodeSpec`, its config and identity;
- :mod:`~afvsgp_gym.evaluation.factories`: :func:`make_env`, :func:`make_policy`;
- :mod:`~afvsgp_gym.evaluation.runner`: :func:`run_episode`, :func:`run_spec`,
  :func:`evaluate` (the counting itself: :class:`afvsgp_gym.episode_counts.EpisodeCounter`);
- :mod:`~afvsgp_gym.evaluation.summary`: :func:`summarize`;
- :mod:`~afvsgp_gym.evaluation.report`: :func:`format_table`, :func:`write_json`,
  :func:`write_csv`;
- :mod:`~afvsgp_gym.evaluation.io`: :func:`jsonable`, :func:`check_writable`;
- :mod:`~afvsgp_gym.evaluation.version`: :func:`code_version`, :func:`cpu_model`.
"""

from afvsgp_gym.episode_counts import CALIBRATION_LEGEND, COST_DEFINITION, SAFE_MARGIN
from afvsgp_gym.evaluation.factories import BUILTIN_AGENTS, Policy, make_env, make_policy
from afvsgp_gym.evaluation.io import check_writable, jsonable
from afvsgp_gym.evaluation.report import format_table, write_csv, write_json
from afvsgp_gym.evaluation.runner import (
    COUNT_FIELDS,
    EPISODE_FIELDS,
    REFERENCE_CLEARANCE,
    evaluate,
    run_episode,
    run_spec,
)
from afvsgp_gym.evaluation.spec import UNFILTERED, EpisodeSpec
from afvsgp_gym.evaluation.summary import SUMMARY_FIELDS, summarize
from afvsgp_gym.evaluation.version import code_version, cpu_model

__all__ = [
    "BUILTIN_AGENTS",
    "CALIBRATION_LEGEND",
    "COST_DEFINITION",
    "COUNT_FIELDS",
    "EPISODE_FIELDS",
    "REFERENCE_CLEARANCE",
    "SAFE_MARGIN",
    "SUMMARY_FIELDS",
    "UNFILTERED",
    "EpisodeSpec",
    "Policy",
    "check_writable",
    "code_version",
    "cpu_model",
    "evaluate",
    "format_table",
    "jsonable",
    "make_env",
    "make_policy",
    "run_episode",
    "run_spec",
    "summarize",
    "write_csv",
    "write_json",
]
