"""cacc-bench: analysis."""
