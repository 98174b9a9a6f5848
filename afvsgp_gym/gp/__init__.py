"""afvsgp_gym.gp."""
