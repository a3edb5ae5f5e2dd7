"""Battery power of each vehicle class, and of a heterogeneous string (kW).

The ``i3`` class keeps the benchmark's own model (the fitted polynomial of the BMW i3 map,
:mod:`envs.energy.power`). Every other class (powertrain ``bev-physics``) is a battery-electric
physics model with its parameters in :data:`envs.vehicle_classes.VEHICLE_CLASSES`::

    F      = m u + m g c_rr [v > 0] + rho/2 C_d A v^2
    P_w    = F v                                   (wheel power, W)
    P_batt = P_w / eta            when P_w >= 0    (motoring)
           = max(P_w eta, -P_regen_max)  otherwise  (regeneration, friction brakes take the rest)
           + P_aux

with ``rho`` 1.204 kg/m^3 and ``g`` 9.81 m/s^2 (the i3 data's constants). Each class is checked
against one published consumption figure on a cycle built from its published definition (the
NEDC, :func:`nedc_speed_mps`; its urban part, :func:`ece15_speed_mps`) by
``tests/test_envs/test_vehicle_class_energy.py``; the figures and the tolerances are in
``docs/vehicle-classes.md``. The platoon's drag saving (scenario option ``drag_saving``, off by
default) is :class:`DragSaving`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from envs.vehicle_classes import VehicleClass

#: Air density and gravity of the physics model (the SUMO i3 data's constants).
AIR_DENSITY_KGM3 = 1.204
GRAVITY_MPS2 = 9.81


def class_power_kw(cls: VehicleClass, speed_mps: np.ndarray,
                   accel_mps2: np.ndarray, drag_scale: np.ndarray | float = 1.0) -> np.ndarray:
    """Battery power (kW, negative = regeneration) of a ``bev-physics`` class at speed (m/s)
    and acceleration (m/s^2), broadcast together (the module docstring's model); ``drag_scale``
    multiplies ``C_d`` (a follower in a wake, :class:`DragSaving`).

    Raises
    ------
    ValueError
        For the ``i3-map`` class, whose power is the polynomial's (:class:`StringPower`).
    """
    if cls.powertrain != "bev-physics":
        raise ValueError(f"class {cls.name} uses the {cls.powertrain} model, not the physics one")
    v = np.maximum(np.asarray(speed_mps, dtype=np.float64), 0.0)
    u = np.asarray(accel_mps2, dtype=np.float64)
    force = (cls.mass_kg * u + np.where(v > 1e-6, cls.mass_kg * GRAVITY_MPS2 * cls.rolling_coeff,
                                        0.0)
             + 0.5 * AIR_DENSITY_KGM3 * cls.drag_coeff * cls.frontal_area_m2 * v * v
             * drag_scale)
    wheel_w = force * v
    eta = cls.drive_efficiency
    battery_w = np.where(wheel_w >= 0, wheel_w / eta,
                         np.maximum(wheel_w * eta, -1000.0 * cls.regen_power_max_kw))
    return (battery_w + 1000.0 * cls.aux_power_kw) / 1000.0


class StringPower:
    """Battery power of every follower of a heterogeneous string, ``(B, N)`` (kW).

    Parameters
    ----------
    classes : tuple of VehicleClass
        The followers' classes, follower 1 first.
    i3_power_kw : callable
        ``(speed (B, k), accel (B, k)) -> (B, k)``: the env's i3 model (the polynomial inside
        its fit domain), used for the ``i3`` seats so that they are scored as in the
        homogeneous platoon.
    """

    def __init__(self, classes: tuple[VehicleClass, ...],
                 i3_power_kw: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> None:
        self.classes = classes
        self._i3 = i3_power_kw
        self._i3_seats = np.array([i for i, c in enumerate(classes) if c.powertrain == "i3-map"],
                                  dtype=np.int64)
        self._groups = [(c, np.array([i for i, d in enumerate(classes) if d == c], np.int64))
                        for c in dict.fromkeys(classes) if c.powertrain == "bev-physics"]

    def __call__(self, speed_mps: np.ndarray, accel_mps2: np.ndarray) -> np.ndarray:
        out = np.empty(np.shape(speed_mps), dtype=np.float64, order="F")
        if self._i3_seats.size:
            out[:, self._i3_seats] = self._i3(speed_mps[:, self._i3_seats],
                                              accel_mps2[:, self._i3_seats])
        for cls, seats in self._groups:
            out[:, seats] = class_power_kw(cls, speed_mps[:, seats], accel_mps2[:, seats])
        return out


# ------------------------------------------------------------------ the platoon's drag saving

#: The measurement the ``cerutti2021`` drag saving is anchored to: Cerutti, Cafiero and Iuso,
#: "Aerodynamic drag reduction by means of platooning configurations of light commercial
#: vehicles: a flow field analysis", Int. J. Heat and Fluid Flow 90 (2021) 108823 (wind tunnel,
#: models of a light commercial vehicle, Re_L 2.3e5). Two-vehicle platoon: the rear vehicle's
#: drag falls by 43 % at a gap of half a vehicle length; the platoon's mean reduction is 20 % at
#: three lengths. Pairs (gap / predecessor's length, drag reduction of the follower).
CERUTTI2021_POINTS: tuple[tuple[float, float], ...] = ((0.5, 0.43), (3.0, 0.20))


def drag_reduction(gap_over_length: np.ndarray) -> np.ndarray:
    """A follower's drag reduction (share of its lone ``C_d``) at ``gap / L`` of its
    predecessor's length ``L``: ``r(x) = r_0 exp(-k (x - x_0))`` through the two points of
    :data:`CERUTTI2021_POINTS` (``r_0 = 0.43`` at ``x_0 = 0.5``, ``0.20`` at 3), held at
    ``r_0`` below ``x_0`` (no extrapolation to savings larger than measured). The second point
    is the two-vehicle platoon's mean, of a front vehicle that saves less than the rear one at
    half a length (30 % against 43 %): as the rear vehicle's it is an underestimate there."""
    (x0, r0), (x1, r1) = CERUTTI2021_POINTS
    k = math.log(r0 / r1) / (x1 - x0)
    x = np.maximum(np.asarray(gap_over_length, dtype=np.float64), x0)
    return r0 * np.exp(-k * (x - x0))


class DragSaving:
    """The battery power a follower saves in its predecessor's wake, ``(B, N)`` (kW, <= 0 while
    motoring): the class physics model with the drag coefficient scaled by ``1 - r(gap / L)``
    (:func:`drag_reduction`) minus the same model unscaled, added to the seat's own power (so an
    ``i3`` seat keeps its efficiency map and gains only the physics model's drag difference).

    ``L`` is the predecessor's length; follower 1's predecessor, the leader, is taken to be of
    follower 1's class. The saving a follower gives its predecessor (the front vehicle's base
    pressure rises too: 30 % at half a length in the same measurement) is left out.

    Parameters
    ----------
    classes : tuple of VehicleClass
        The followers' classes (the homogeneous platoon: N times the ``i3`` class).
    """

    def __init__(self, classes: tuple[VehicleClass, ...]) -> None:
        self.classes = classes
        self._length = np.array([classes[0].length_m] + [c.length_m for c in classes[:-1]])
        # the physics model of each class (of an i3 seat too: its drag difference in the wake)
        self._groups = [(dataclasses.replace(c, powertrain="bev-physics"),
                         np.array([i for i, d in enumerate(classes) if d == c], np.int64))
                        for c in dict.fromkeys(classes)]

    def delta_kw(self, gap_m: np.ndarray, speed_mps: np.ndarray,
                 accel_mps2: np.ndarray) -> np.ndarray:
        """The change of each follower's battery power (kW) in the wake at these gaps, speeds
        and accelerations ``(B, N)``."""
        scale = 1.0 - drag_reduction(np.asarray(gap_m) / self._length)
        out = np.empty(np.shape(speed_mps), dtype=np.float64)
        for phys, seats in self._groups:
            v, u = speed_mps[:, seats], accel_mps2[:, seats]
            out[:, seats] = (class_power_kw(phys, v, u, scale[:, seats])
                             - class_power_kw(phys, v, u))
        return out


# ------------------------------------------------------------------------ the NEDC, for checks

#: The NEDC's urban part (ECE-15, UNECE Regulation 83 Annex 4a, Appendix 1): 15 speed segments
#: of one elementary cycle as (duration s, speed at the end km/h), linear in between, from rest.
#: Gear-change pauses hold the speed. 195 s, 1.013 km (published).
_ECE15_SEGMENTS: tuple[tuple[float, float], ...] = (
    (11, 0), (4, 15), (8, 15), (2, 10), (3, 0), (21, 0), (5, 15), (2, 15), (5, 32), (24, 32),
    (8, 10), (3, 0), (21, 0), (5, 15), (2, 15), (9, 35), (2, 35), (8, 50), (12, 50), (8, 35),
    (13, 35), (2, 35), (7, 10), (3, 0), (7, 0),
)
#: The extra-urban part (EUDC, same annex): 400 s, 6.955 km (published).
_EUDC_SEGMENTS: tuple[tuple[float, float], ...] = (
    (20, 0), (5, 15), (2, 15), (9, 35), (2, 35), (8, 50), (2, 50), (13, 70), (50, 70), (8, 50),
    (69, 50), (13, 70), (50, 70), (35, 100), (30, 100), (20, 120), (10, 120), (16, 80), (8, 50),
    (10, 0), (20, 0),
)


def _piecewise(segments: tuple[tuple[float, float], ...], dt_s: float) -> np.ndarray:
    times = np.concatenate([[0.0], np.cumsum([d for d, _ in segments])])
    speeds = np.concatenate([[0.0], [v for _, v in segments]]) / 3.6
    t = np.arange(0.0, times[-1] + 1e-9, dt_s)
    return np.interp(t, times, speeds)


def ece15_speed_mps(dt_s: float = 0.1, cycles: int = 4) -> np.ndarray:
    """The NEDC's urban part alone: ``cycles`` ECE-15 elementary cycles (195 s, 1.013 km each),
    sampled every ``dt_s`` (m/s): the urban stop-and-go cycle of the bus check."""
    ece = _piecewise(_ECE15_SEGMENTS, dt_s)
    return np.concatenate([ece[:-1]] * (cycles - 1) + [ece])


def nedc_speed_mps(dt_s: float = 0.1) -> np.ndarray:
    """The NEDC speed trace (four ECE-15 cycles, then the EUDC), sampled every ``dt_s`` (m/s):
    1180 s and 11.007 km as published (UNECE R83/R101)."""
    ece = _piecewise(_ECE15_SEGMENTS, dt_s)
    eudc = _piecewise(_EUDC_SEGMENTS, dt_s)
    return np.concatenate([ece[:-1]] * 4 + [eudc])


def cycle_kwh_per_100km(power_kw: Callable[[np.ndarray, np.ndarray], np.ndarray],
                        speed_mps: np.ndarray, dt_s: float) -> float:
    """Battery energy per 100 km of a model ``power_kw(v, u)`` over a speed trace: the
    acceleration of each step ``(v[k+1] - v[k]) / dt`` at the step's mean speed, rectangle rule.
    """
    v = np.asarray(speed_mps, dtype=np.float64)
    u = np.diff(v) / dt_s
    vm = 0.5 * (v[1:] + v[:-1])
    energy_kwh = float(np.sum(power_kw(vm, u)) * dt_s / 3600.0)
    distance_m = float(np.sum(vm) * dt_s)
    return energy_kwh * 1e5 / distance_m
