"""What a controller that runs inside SUMO asks of the SUMO env: a car-following model of SUMO's
for the automated seats, its vehicle-type attributes and the parameters set on each vehicle.

The controllers (``sumo:acc``, ``sumo:cacc``, ``plexe:ploeg``, ``plexe:path``,
:mod:`controllers.sumo_models`) describe their model with a :class:`SumoModel`; the env
(:class:`envs.sumo.env.SumoPlatoonEnv`) builds the vehicle type, inserts the automated seats with
it and lets SUMO compute their speeds (it does not command them).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class SumoModel:
    """A SUMO car-following model for the automated seats.

    Attributes
    ----------
    car_follow_model : str
        SUMO's ``carFollowModel`` (``ACC``, ``CACC``, ``CC``).
    vtype : dict of str to str
        Further ``vType`` attributes (the model's parameters, ``minGap``, ``accel``, ...).
    vehicle_parameters : dict of str to str
        ``libsumo.vehicle.setParameter`` keys and values set on every automated vehicle once it
        is inserted (Plexe's ``carFollowModel.ccac`` selects the controller).
    speed_mode : int or None
        ``setSpeedMode`` of the automated vehicles (None: SUMO's default, 31).
    """

    car_follow_model: str
    vtype: dict[str, str] = field(default_factory=dict)
    vehicle_parameters: dict[str, str] = field(default_factory=dict)
    speed_mode: int | None = None
