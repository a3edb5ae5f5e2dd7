"""Ranges that keep a command's work finite and allocatable: one rule and one message each,
checked by every command that takes the number before any work."""

from __future__ import annotations

import math

import numpy as np

from infra.errors import ConfigError

#: Longest V2V delay (s): an episode lasts 60 s, so a longer delay delivers no message at all
#: (and its buffer of delay / dt steps must stay allocatable).
MAX_V2V_DELAY_S = 60.0
#: Seeds feed 32-bit generators (numpy, torch, Optuna's sampler with ``seed + trial``).
MAX_SEED = 2**31 - 1
#: Followers N of a platoon, the range every command and scenario checks.
MIN_VEHICLES = 2
MAX_VEHICLES = 64
#: Most environment steps one training run may ask for (the paper's budget is 6e5).
MAX_TRAIN_STEPS = 10**8
#: Most episodes one learner steps together.
MAX_EPISODES_PARALLEL = 4096
#: Widest hidden layer of the shared-policy learners and the distilled actor (64 shipped).
MAX_HIDDEN = 1024
#: Most agent-steps one rollout of a shared-policy learner holds (``n_envs x rollout_steps x
#: N``): its observations, actions and returns must stay allocatable (the default holds 32,768).
MAX_ROLLOUT_AGENT_STEPS = 2**24
#: Training episode k of run seed s has env seed ``TRAIN_SEED_STRIDE * (s + 1) + k``
#: (:meth:`marl.a2c.Run.training_seeds`), drawn by 32-bit generators.
TRAIN_SEED_STRIDE = 10_000_000
#: Largest training seed whose episode seeds stay below 2**32 for a longest run (418).
MAX_TRAIN_SEED = (2**32 - 1 - MAX_TRAIN_STEPS - MAX_EPISODES_PARALLEL) // TRAIN_SEED_STRIDE - 1
#: Largest time gap (s) of a controller's spacing policy (``acc``/``cacc``, the SUMO and Plexe
#: models, ``stability --time-gap``): wide around any platoon (the IDM's range is 0.5-3 s),
#: narrow enough that the spacing a run records and the analytic loop stay finite (``1e13`` s
#: ran, then its record's spacing of 1e14 m was refused; ``1e308`` overflowed the analysis).
MAX_TIME_GAP_S = 10.0
#: Most steps of one episode of a scenario of one's own (10 minutes at 0.1 s; the built-ins'
#: longest, the ring, has 3000): a rollout's arrays of (steps x episodes x followers) must
#: stay allocatable (``10**12`` steps asked for 7 TiB).
MAX_EPISODE_STEPS = 6000
#: Largest distance (m) of a spacing policy (a standstill distance, a constant spacing): wide
#: around any platoon, finite in every metric (``1e308`` m was stored, then refused).
MAX_SPACING_M = 100.0
#: Largest feedback gain of the linear laws (kp in 1/s^2, kd in 1/s): at 100 a spacing error
#: of 2.5 cm already commands the 2.5 m/s^2 bound, so a larger gain is only a switch (``kp=1e308``
#: ran as one, and the frequency sweep called it string stable).
MAX_LINEAR_GAIN = 100.0


def training_episode_seeds(run_seed: int, first: int, count: int) -> np.ndarray:
    """Env seeds of training episodes ``first .. first + count - 1`` of run seed ``run_seed``:
    ``TRAIN_SEED_STRIDE (run_seed + 1) + k`` (the one rule every learner draws its episodes by;
    never a validation, evaluation or test seed, :mod:`envs.params`)."""
    return TRAIN_SEED_STRIDE * (int(run_seed) + 1) + int(first) + np.arange(count)


def check_delay(value: float, flag: str) -> float:
    """``value`` if it is a V2V delay in [0, :data:`MAX_V2V_DELAY_S`] s, else a ConfigError."""
    if not (math.isfinite(value) and 0 <= value <= MAX_V2V_DELAY_S):
        raise ConfigError(f"{flag} must lie in [0, {MAX_V2V_DELAY_S:g}] s (an episode lasts "
                          f"60 s), got {value}")
    return float(value)


def step_count(text: str) -> int:
    """A step budget as ``--steps`` takes it: ``600000``, ``6e5`` or ``6_00_000`` (an integer
    written as a float is read exactly; ``6.5`` or ``abc`` is refused)."""
    import argparse

    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of steps, got {text!r}") from None
    if not (math.isfinite(value) and value == int(value)):
        raise argparse.ArgumentTypeError(f"expected a whole number of steps, got {text!r}")
    return int(value)


def check_whole_steps(value: float, flag: str, dt_s: float) -> float:
    """``value`` if it is a whole number of simulation steps of ``dt_s`` (the platoon's,
    :class:`envs.params.PlatoonParams`), else a ConfigError (a V2V delay is delivered after
    whole steps: 0.05 s would run as 0.1 s and be stored as 0.05)."""
    steps = value / dt_s
    if abs(steps - round(steps)) > 1e-6:
        raise ConfigError(f"{flag} {value:g} s: V2V messages arrive after whole simulation steps "
                          f"of {dt_s:g} s; give a multiple of {dt_s:g} s (0, {dt_s:g}, "
                          f"{2 * dt_s:g}, ...)")
    return float(value)


def check_hidden(value: int, flag: str = "hidden") -> int:
    """``value`` if it is a hidden-layer width in 1..:data:`MAX_HIDDEN`, else a ConfigError (the
    one rule of every learner's config: the paper's learners, the shared ones, the distiller)."""
    if not 1 <= value <= MAX_HIDDEN:
        raise ConfigError(f"{flag} must lie in 1..{MAX_HIDDEN:,}, got {value}")
    return int(value)


def check_packet_loss(value: float, flag: str = "the packet loss") -> float:
    """``value`` if it is a V2V packet-loss probability in [0, 1], else a ConfigError (the one
    rule: :class:`envs.channel.ChannelConfig` and every command's ``--packet-loss``)."""
    if not (math.isfinite(value) and 0 <= value <= 1):
        raise ConfigError(f"{flag} must lie in [0, 1], got {value}")
    return float(value)


def check_seeds(seeds: list[int] | tuple[int, ...], flag: str, high: int = MAX_SEED
                ) -> list[int]:
    """``seeds`` if each lies in 0..``high`` (:data:`MAX_SEED`; training seeds of the MARL
    learners: :data:`MAX_TRAIN_SEED`), else a ConfigError."""
    return [check_range(s, flag, 0, high) for s in seeds]


def check_range(value: int, flag: str, low: int, high: int) -> int:
    """``value`` if ``low <= value <= high``, else a ConfigError naming ``flag``."""
    if not low <= value <= high:
        raise ConfigError(f"{flag} must lie in {low}..{high}, got {value}")
    return value


def check_nonnegative(value: float, name: str, *, positive: bool = False) -> float:
    """``value`` as a float if it is a finite number >= 0 (> 0 with ``positive``), else a
    ConfigError naming ``name`` (the one check of a physical setting given from Python: a
    frequency, an amplitude, a lag, a duration)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ConfigError(f"{name} must be a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out) or out < 0 or (positive and out == 0):
        raise ConfigError(f"{name} must be {'> 0' if positive else '>= 0'}, got {value!r}")
    return out
