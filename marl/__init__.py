"""cacc-bench: marl."""
