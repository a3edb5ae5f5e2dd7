"""Errors that cacc-bench reports to users as a message and exit status 2."""

from __future__ import annotations

from collections.abc import Iterable


class CaccBenchError(Exception):
    """Base class of the errors that a user can fix (bad input, missing file, ...).

    The command line turns these into a one-paragraph message and exit status 2.
    """


class ConfigError(CaccBenchError, ValueError):
    """An impossible or out-of-range setting (negative delay, N < 2, ...)."""


class UnknownNameError(CaccBenchError, KeyError):
    """An unknown registered name (scenario, controller, algorithm)."""

    def __init__(self, kind: str, name: str, valid: Iterable[str], hint: str = "") -> None:
        self.kind = kind
        self.name = name
        self.valid = sorted(valid)
        more = f"; {hint}" if hint else ""
        super().__init__(f"unknown {kind} {name!r}; valid {kind}s are: "
                         f"{', '.join(self.valid)}{more}")

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


class TrainingDivergedError(CaccBenchError, RuntimeError):
    """A learner's weights became non-finite (NaN or infinite) during training."""


class ControllerContractError(RuntimeError):
    """A controller broke the closed loop's contract (a command of the wrong shape, or not
    finite): a defect of the controller, reported as a failed run, never stored as a result."""
