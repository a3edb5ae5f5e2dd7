"""cacc-bench: envs."""
