"""Seeded sweeps at scale: a grid of episodes from a CONFIG file, run by an executor (local
process pool or Ray), appended to a resumable JSON-lines results file, and reported with
Clopper-Pearson bounds on the per-episode cost rate.

- :func:`~afvsgp_gym.sweep.config.load_config` -> :class:`~afvsgp_gym.sweep.config.Sweep`
- :func:`~afvsgp_gym.sweep.validate.validate` (before anything runs)
- :func:`~afvsgp_gym.sweep.runner.run_sweep` with an executor of
  :mod:`afvsgp_gym.executors`
- :func:`~afvsgp_gym.sweep.report.report`, :func:`~afvsgp_gym.sweep.plot.plot_report`
"""

from afvsgp_gym.executors import (
    InlineExecutor,
    LocalExecutor,
    RayExecutor,
    make_executor,
)
from afvsgp_gym.sweep.config import ConfigError, Sweep, load_config, parse_config
from afvsgp_gym.sweep.report import format_report, report, write_report_json
from afvsgp_gym.sweep.results import ResultsLog, read_records
from afvsgp_gym.sweep.runner import SweepResult, run_sweep
from afvsgp_gym.sweep.validate import validate

__all__ = [
    "ConfigError",
    "InlineExecutor",
    "LocalExecutor",
    "RayExecutor",
    "ResultsLog",
    "Sweep",
    "SweepResult",
    "format_report",
    "load_config",
    "make_executor",
    "parse_config",
    "read_records",
    "report",
    "run_sweep",
    "validate",
    "write_report_json",
]
