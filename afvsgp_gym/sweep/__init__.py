"""Running many seeded episodes: executors (in-process, a local process pool, Ray) and the
progress bar over episodes."""
