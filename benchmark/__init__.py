"""cacc-bench: benchmark."""
