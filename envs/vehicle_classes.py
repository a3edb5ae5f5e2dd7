"""Vehicle classes of heterogeneous platoons: named presets with their public sources, the
``classes`` / ``class_mix`` arrangement grammar, and the per-vehicle arrays of the dynamics.

Every number of a preset and its source is listed in ``docs/vehicle-classes.md``; the short
form is in each preset's ``sources``. The homogeneous platoon (no ``classes`` option) has no
classes at all: the env then runs the published model (``envs.params.PlatoonParams``) unchanged.

Arrangement grammar (scenario options, parsed once by :func:`parse_class_sequence`)
-----------------------------------------------------------------------------------
``classes=bus+van+car*6``
    The followers' classes front to back; ``name*k`` repeats a class ``k`` times. The sequence
    must name exactly N classes (checked when N is known, :func:`classes_for`).
``class_mix=car*6+van+bus`` (with ``class_seed``)
    The same multiset, shuffled by the stream ``class-mix`` of ``class_seed`` (the same order
    for every episode of the scenario): a seeded mix.

Per-vehicle limits
------------------
A class gives its own actuator lag ``tau`` and acceleration bounds. The bounds a vehicle gets
are the tighter of the class's and the run's (:class:`envs.params.PlatoonParams`, the
published +-2.5 m/s^2): a bus accelerates at most 1.2 m/s^2, and no class brakes harder than
the published bound. The class lag replaces ``PlatoonParams.lag_s``, which must then be 0 (a
run-wide lag and per-class lags at once are refused, :func:`vehicle_arrays`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from envs.params import PlatoonParams
from envs.streams import episode_stream
from infra.errors import ConfigError

#: Stream name of the seeded class mix (``class_mix`` with ``class_seed``).
CLASS_MIX_STREAM = "class-mix"
#: The scenario options that set the followers' classes.
CLASS_OPTIONS: tuple[str, ...] = ("classes", "class_mix", "class_seed")


def zheng_lag_s(mass_kg: float) -> float:
    """Actuator lag of a light vehicle by Zheng et al.'s rule, ``0.5 + 0.3 (m - 1000)/1000`` s,
    with the mass clipped to the rule's range [1000, 2000] kg (Zheng, Li, Li, Borrelli, Hedrick,
    IEEE T-CST 25(3), 2017; their code ``soc-ucsd/DMPC_for_platoons``, ``Parameter_Initial.m``)."""
    m = min(max(float(mass_kg), 1000.0), 2000.0)
    return 0.5 + 0.3 * (m - 1000.0) / 1000.0


@dataclass(frozen=True)
class VehicleClass:
    """One vehicle class: body, powertrain and longitudinal limits (units in names).

    Attributes
    ----------
    name : str
        The name on the command line (``car``, ``i3``, ``van``, ``bus``, ``truck``).
    description : str
        What it stands for.
    mass_kg : float
        Test mass (curb mass, plus the trailer for the truck).
    drag_coeff, frontal_area_m2, rolling_coeff : float
        ``C_d``, ``A`` and ``c_rr`` of the road-load force ``m g c_rr + rho/2 C_d A v^2``.
    lag_s : float
        First-order actuator lag ``tau`` (s).
    accel_max_mps2, decel_max_mps2 : float
        The class's acceleration and (positive) deceleration capability.
    length_m : float
        Vehicle length.
    standstill_gap_m : float
        Standstill gap (SUMO's ``minGap``; 2.5 m by default).
    powertrain : str
        ``"i3-map"``: the BMW i3 efficiency map and its fitted polynomial (the env's energy
        model); ``"bev-physics"`` (the default): the battery-electric physics model of
        :mod:`envs.energy.classes`.
    drive_efficiency : float
        Battery-to-wheel efficiency when motoring (and wheel-to-battery when regenerating;
        0.85 by default).
    regen_power_max_kw : float
        Regenerative braking power limit (friction brakes take the rest).
    aux_power_kw : float
        Constant auxiliary load.
    sources : str
        The public sources of these numbers, in short (the full list: ``docs/vehicle-classes.md``).
    """

    name: str
    description: str
    mass_kg: float
    drag_coeff: float
    frontal_area_m2: float
    rolling_coeff: float
    lag_s: float
    accel_max_mps2: float
    decel_max_mps2: float
    length_m: float
    regen_power_max_kw: float
    aux_power_kw: float
    sources: str
    standstill_gap_m: float = 2.5
    powertrain: str = "bev-physics"
    drive_efficiency: float = 0.85

    def __post_init__(self) -> None:
        positive = ("mass_kg", "drag_coeff", "frontal_area_m2", "rolling_coeff",
                    "accel_max_mps2", "decel_max_mps2", "length_m", "drive_efficiency")
        for key in positive:
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"vehicle class {self.name}: {key} must be > 0, got {value}")
        if not (math.isfinite(self.lag_s) and self.lag_s >= 0):
            raise ConfigError(f"vehicle class {self.name}: lag_s must be >= 0, got {self.lag_s}")
        if self.drive_efficiency > 1:
            raise ConfigError(f"vehicle class {self.name}: drive_efficiency must be <= 1")
        if self.powertrain not in POWERTRAINS:
            raise ConfigError(f"vehicle class {self.name}: powertrain must be one of "
                              f"{', '.join(POWERTRAINS)}, got {self.powertrain!r}")


#: Powertrain models of a class (:mod:`envs.energy.classes`).
POWERTRAINS: tuple[str, ...] = ("i3-map", "bev-physics")

_SUMO_PASSENGER = "SUMO vClass passenger defaults (accel 2.6, decel 4.5 m/s^2, minGap 2.5 m)"

#: The registered classes, by name (``docs/vehicle-classes.md`` gives every source in full).
VEHICLE_CLASSES: dict[str, VehicleClass] = {c.name: c for c in (
    VehicleClass(
        "car", "small car (Saturn SL1 body of NREL ADVISOR's VEH_SMCAR), battery-electric",
        mass_kg=1191.0, drag_coeff=0.335, frontal_area_m2=2.0, rolling_coeff=0.009,
        lag_s=round(zheng_lag_s(1191.0), 3), accel_max_mps2=2.6, decel_max_mps2=4.5,
        length_m=4.4, regen_power_max_kw=40.0, aux_power_kw=0.36,
        sources="body: ADVISOR VEH_SMCAR; lag: Zheng et al. 2017 rule; limits: "
                + _SUMO_PASSENGER),
    VehicleClass(
        "i3", "BMW i3 (2013-2017, 125 kW): the car of the benchmark's energy model",
        mass_kg=1417.0, drag_coeff=0.29, frontal_area_m2=2.38, rolling_coeff=0.007,
        lag_s=round(zheng_lag_s(1417.0), 3), accel_max_mps2=2.6, decel_max_mps2=4.5,
        length_m=4.0, regen_power_max_kw=50.0, aux_power_kw=0.36, powertrain="i3-map",
        sources="body and powertrain: SUMO MMPEVEM bmw_i3.dat (Koch et al. ITSC 2021); lag: "
                "Zheng et al. 2017 rule; limits: " + _SUMO_PASSENGER),
    VehicleClass(
        "van", "full-size cargo van (NREL ADVISOR VEH_cargoVan body), battery-electric",
        mass_kg=2182.0, drag_coeff=0.45, frontal_area_m2=3.4, rolling_coeff=0.009,
        lag_s=round(zheng_lag_s(2182.0), 3), accel_max_mps2=2.6, decel_max_mps2=4.5,
        length_m=6.5, regen_power_max_kw=60.0, aux_power_kw=0.5,
        sources="body: ADVISOR VEH_cargoVan; lag: Zheng et al. 2017 rule at its 2000 kg end; "
                "limits and length: SUMO vClass delivery defaults"),
    VehicleClass(
        "bus", "40 ft transit bus (Nova RTS-06 body of NREL ADVISOR's VEH_RTS06), "
               "battery-electric",
        mass_kg=12156.0, drag_coeff=0.79, frontal_area_m2=7.9, rolling_coeff=0.00938,
        lag_s=0.8, accel_max_mps2=1.2, decel_max_mps2=4.0,
        length_m=12.0, regen_power_max_kw=150.0, aux_power_kw=5.0,
        sources="body: ADVISOR VEH_RTS06; limits and length: SUMO vClass bus defaults; lag: "
                "assumed, the top of Zheng et al.'s range (no public source for a bus)"),
    VehicleClass(
        "truck", "tractor-trailer (Kenworth T800 with a 12.7 t trailer, NREL ADVISOR "
                 "VEH_KENT800), battery-electric",
        mass_kg=18506.0, drag_coeff=0.70, frontal_area_m2=8.55, rolling_coeff=0.008,
        lag_s=0.8, accel_max_mps2=1.3, decel_max_mps2=4.0,
        length_m=16.5, regen_power_max_kw=200.0, aux_power_kw=2.0,
        sources="body: ADVISOR VEH_KENT800; limits: SUMO vClass truck defaults, length: SUMO "
                "trailer; lag: assumed, as the bus"),
)}


#: The platoon drag-saving models of the scenario option ``drag_saving`` (off: ``none``, the
#: default); the model itself is :func:`envs.energy.classes.drag_reduction`.
DRAG_SAVING_MODELS: tuple[str, ...] = ("none", "cerutti2021")


def check_drag_saving(value: str, who: str) -> None:
    """The rule of the scenario option ``drag_saving``: one of :data:`DRAG_SAVING_MODELS`.

    Raises
    ------
    ConfigError
        For any other value.
    """
    if value not in DRAG_SAVING_MODELS:
        raise ConfigError(f"{who}: drag_saving must be one of {', '.join(DRAG_SAVING_MODELS)} "
                          f"(none: no platoon drag saving, the default), got {value!r}")


def vehicle_class(name: str, who: str = "classes") -> VehicleClass:
    """The registered class ``name``, else a ConfigError listing the classes."""
    try:
        return VEHICLE_CLASSES[name]
    except KeyError:
        raise ConfigError(f"{who}: unknown vehicle class {name!r}; the classes are "
                          f"{', '.join(VEHICLE_CLASSES)}") from None


def parse_class_sequence(text: str, who: str = "classes") -> tuple[str, ...]:
    """The class names of ``text`` (``"bus+van+car*6"``), in order, ``name*k`` expanded.

    Raises
    ------
    ConfigError
        For an empty item, an unknown class, a repeat that is not a whole number >= 1 (ASCII
        digits), or more classes than a platoon has (``infra.limits.MAX_VEHICLES``).
    """
    from infra.limits import MAX_VEHICLES  # the platoon's limit

    out: list[str] = []
    for raw in text.split("+"):
        item = raw.strip()
        name, star, count = item.partition("*")
        k = 1
        if star:
            digits = count.strip()  # ASCII digits only: int() refuses '²', which isdigit() takes
            if not (digits.isascii() and digits.isdigit()) or int(digits) < 1:
                raise ConfigError(f"{who}={text!r}: a repeat is name*k with a whole k >= 1 "
                                  f"(car*6), got {item!r}")
            k = int(digits)
        if not name.strip():
            raise ConfigError(f"{who}={text!r} has an empty item; join class names with '+' "
                              "(bus+van+car*6)")
        vehicle_class(name.strip(), who)
        if len(out) + k > MAX_VEHICLES:  # before the list is made: car*10**12 is no platoon
            raise ConfigError(f"{who}={text!r} names more than {MAX_VEHICLES} vehicles, the "
                              "most a platoon has; give one class per follower")
        out.extend([name.strip()] * k)
    return tuple(out)


def canonical_classes(names: tuple[str, ...]) -> str:
    """One spelling of a class sequence: runs of a class written ``name*k``
    (``("car", "car", "van")`` -> ``"car*2+van"``)."""
    runs = [(name, len(list(run))) for name, run in itertools.groupby(names)]
    return "+".join(name if k == 1 else f"{name}*{k}" for name, k in runs)


def classes_for(classes: str, class_mix: str, class_seed: int, n_vehicles: int,
                who: str) -> tuple[VehicleClass, ...] | None:
    """The classes of the N followers of a scenario's options, or None without classes.

    Raises
    ------
    ConfigError
        When the sequence does not name exactly ``n_vehicles`` classes.
    """
    if not classes and not class_mix:
        return None
    option = "classes" if classes else "class_mix"
    names = parse_class_sequence(classes or class_mix, option)
    if len(names) != n_vehicles:
        raise ConfigError(f"{who}: {option} names {len(names)} vehicles but the run has "
                          f"{n_vehicles} followers; give exactly {n_vehicles} "
                          f"(name*k repeats a class: car*{n_vehicles})")
    if class_mix:
        order = episode_stream(int(class_seed), CLASS_MIX_STREAM).permutation(n_vehicles)
        names = tuple(names[int(i)] for i in order)
    return tuple(VEHICLE_CLASSES[n] for n in names)


@dataclass(frozen=True)
class VehicleArrays:
    """Per-vehicle limits of a heterogeneous string, ``(N,)`` each, as the dynamics use them.

    Attributes
    ----------
    classes : tuple of VehicleClass
        Follower 1 first.
    lag_s, lag_gain : (N,)
        Actuator lags and ``1 - exp(-dt/tau)`` (1 without lag).
    accel_min_mps2, accel_max_mps2 : (N,)
        The tighter of the class's and the run's bounds.
    """

    classes: tuple[VehicleClass, ...]
    lag_s: np.ndarray
    lag_gain: np.ndarray
    accel_min_mps2: np.ndarray
    accel_max_mps2: np.ndarray

    @property
    def names(self) -> tuple[str, ...]:
        """Class names, follower 1 first."""
        return tuple(c.name for c in self.classes)

    @property
    def has_lag(self) -> np.ndarray:
        """``(N,)`` booleans: the vehicle has an actuator lag."""
        return self.lag_s > 0


def vehicle_arrays(classes: tuple[VehicleClass, ...], params: PlatoonParams,
                   who: str = "classes") -> VehicleArrays:
    """The per-vehicle arrays of ``classes`` in a run with ``params``.

    Raises
    ------
    ConfigError
        When ``params`` also sets a run-wide actuator lag.
    """
    if params.lag_s > 0:
        raise ConfigError(f"{who}: the vehicle classes set every vehicle's actuator lag "
                          f"({', '.join(sorted({f'{c.name} {c.lag_s:g} s' for c in classes}))}); "
                          f"a run-wide lag ({params.lag_s:g} s) would replace them: leave the "
                          "lag out (--lag)")
    lag = np.array([c.lag_s for c in classes], dtype=np.float64)
    # 1 - exp(-dt/tau), as PlatoonParams.lag_gain computes it (the same bits for the same lag)
    gain = np.array([1.0 - math.exp(-params.dt_s / t) if t > 0 else 1.0 for t in lag])
    amax = np.minimum([c.accel_max_mps2 for c in classes], params.accel_max_mps2)
    amin = np.maximum([-c.decel_max_mps2 for c in classes], params.accel_min_mps2)
    return VehicleArrays(tuple(classes), lag, gain, amin.astype(np.float64),
                         amax.astype(np.float64))


# ---------------------------------------------------------------------------- class features
#: Names of the class features a shared policy trained with ``class_features`` reads after its
#: observation (:func:`class_features`), in order: the actuator lag over
#: :data:`CLASS_LAG_SCALE_S`, the acceleration bound over the run's, and ``log10`` of the mass
#: over 1000 kg. (The braking bound is not one: no class brakes less hard than the run's bound,
#: so it is the run's for every vehicle, a constant column.)
CLASS_FEATURE_NAMES: tuple[str, ...] = ("lag", "accel_max", "log_mass")
#: The lag that maps to the feature 1 (s).
CLASS_LAG_SCALE_S: float = 1.0
#: The mass that maps to the feature 0 (kg).
CLASS_MASS_SCALE_KG: float = 1000.0
#: The class whose mass the homogeneous (published) platoon's features carry: the car of the
#: energy model.
HOMOGENEOUS_CLASS: str = "i3"


def class_features(vehicles: VehicleArrays | None, n_vehicles: int,
                   params: PlatoonParams) -> np.ndarray:
    """Each follower's own class parameters, normalised: ``(N, F)`` float32, columns
    :data:`CLASS_FEATURE_NAMES`.

    The lag and the acceleration bound are what the dynamics use (:class:`VehicleArrays`: the
    class lag, the tighter of the class's and the run's bound). The homogeneous platoon
    (``vehicles`` None) gets the published platoon's: the run's lag (``params.lag_s``, 0 by
    default) and bound, and the mass of the energy model's car (:data:`HOMOGENEOUS_CLASS`).
    """
    if vehicles is None:
        lag = np.full(n_vehicles, params.lag_s)
        amax = np.full(n_vehicles, params.accel_max_mps2)
        mass = np.full(n_vehicles, VEHICLE_CLASSES[HOMOGENEOUS_CLASS].mass_kg)
    else:
        if len(vehicles.classes) != n_vehicles:
            raise ValueError(f"{len(vehicles.classes)} classes for {n_vehicles} followers")
        lag, amax = vehicles.lag_s, vehicles.accel_max_mps2
        mass = np.array([c.mass_kg for c in vehicles.classes])
    out = np.stack([lag / CLASS_LAG_SCALE_S, amax / params.accel_max_mps2,
                    np.log10(mass / CLASS_MASS_SCALE_KG)], axis=-1)
    return out.astype(np.float32)
