"""afvsgp_gym.envs."""
