"""Policies for the afvsgp_gym environments."""

from afvsgp_gym.agents.nominal import NominalController

__all__ = ["NominalController"]
