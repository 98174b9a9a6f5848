"""afvsgp_gym.cbf."""
