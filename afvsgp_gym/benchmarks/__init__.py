"""afvsgp_gym.benchmarks."""
