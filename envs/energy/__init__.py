"""Battery power models of an electric car: efficiency-map model, fitted polynomial, VT-CPEM.

Follows ``docs/spec/energy.md``. Three models of the battery power ``P(v, u)`` (kW) of one car driving
at speed ``v`` (m/s) with acceleration ``u`` (m/s^2):

``"map"``
    The efficiency-map model of a BMW i3 built from the public SUMO MMPEVEM data
    (``data/energy/bmw_i3.dat``, EPL-2.0, Koch et al., ITSC 2021): wheel force -> wheel torque ->
    motor torque through the gearbox -> motor torque and power limits -> battery power
    ``P_batt = T_m omega_m + P_loss(n, T_m) + P_aux`` with the motor + inverter loss from the loss
    map. See :func:`map_operating_point`.
``"poly"``
    The fitted model ``P(v, u) = max(sum_k sum_j p[k, j] v^k u^j, floor(v))``: a 5 x 5 polynomial
    where regeneration is not limited and the regeneration-limited power as a cubic ``floor(v)``,
    fitted to the map model by :func:`fit_power_polynomial` and shipped in
    ``data/energy/power_poly.json``. This is the one model that the reward, the MPC cost and the
    energy metric use. :class:`PowerPolynomial` is its fast evaluator.
``"vtcpem"``
    The VT-CPEM model of a Nissan Leaf (Fiori, Ahn, Rakha, Applied Energy 168, 2016), for
    sensitivity studies. See :func:`vtcpem_battery_power_kw`.

Sign convention: positive power is drawn from the battery, negative power (regeneration) flows
into it. Only numpy is imported; nothing here reads files outside the package's data folder.

The modules: :mod:`envs.energy.vehicle` (data), :mod:`envs.energy.map_model` (physical
models), :mod:`envs.energy.power` (runtime model) with its kernel :mod:`envs.energy.horner`,
:mod:`envs.energy.fit` (offline fit).
"""

from __future__ import annotations

from envs.energy.fit import PowerFit, fit_power_polynomial
from envs.energy.map_model import (
    MotorOperatingPoint,
    VTCPEMParams,
    map_battery_power_kw,
    map_operating_point,
    vtcpem_battery_power_kw,
)
from envs.energy.power import (
    MODELS,
    PowerPolynomial,
    battery_power_kw,
    energy_kwh,
    kwh_per_100km,
    load_power_polynomial,
)
from envs.energy.vehicle import (
    DATA_DIR,
    DEFAULT_POLYNOMIAL_FILE,
    DEFAULT_VEHICLE_FILE,
    EnergyDataError,
    LossMap,
    VehicleParams,
    load_loss_map,
    load_vehicle_params,
)

__all__ = [
    "DATA_DIR",
    "DEFAULT_POLYNOMIAL_FILE",
    "DEFAULT_VEHICLE_FILE",
    "MODELS",
    "EnergyDataError",
    "LossMap",
    "MotorOperatingPoint",
    "PowerFit",
    "PowerPolynomial",
    "VTCPEMParams",
    "VehicleParams",
    "battery_power_kw",
    "energy_kwh",
    "fit_power_polynomial",
    "kwh_per_100km",
    "load_loss_map",
    "load_power_polynomial",
    "load_vehicle_params",
    "map_battery_power_kw",
    "map_operating_point",
    "vtcpem_battery_power_kw",
]
