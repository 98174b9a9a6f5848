"""afvsgp_gym.wrappers."""
