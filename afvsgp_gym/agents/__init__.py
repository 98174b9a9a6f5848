"""afvsgp_gym.agents."""
