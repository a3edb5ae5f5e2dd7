"""cacc-bench: controllers."""
