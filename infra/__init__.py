"""What every layer of cacc-bench stands on: the errors a user can fix, the limits and their
checks, the label grammar of names with options, atomic file writes, the reading of input files
(JSON, CSV), signal handling.

The bottom layer: it imports none of the project's packages (``envs`` and everything above it
import it).
"""
