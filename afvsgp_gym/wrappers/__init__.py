"""afvsgp_gym.wrappers: the SafetyFilter Gymnasium wrapper."""

from afvsgp_gym.wrappers.safety_filter import SafetyFilter

__all__ = ["SafetyFilter"]
