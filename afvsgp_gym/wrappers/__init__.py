"""afvsgp_gym.wrappers: the SafetyFilter Gymnasium wrapper and the RL training wrappers."""

from afvsgp_gym.wrappers.action_repeat import ActionRepeat
from afvsgp_gym.wrappers.episode_safety import EpisodeSafetyStats
from afvsgp_gym.wrappers.safety_filter import SafetyFilter

__all__ = ["ActionRepeat", "EpisodeSafetyStats", "SafetyFilter"]
