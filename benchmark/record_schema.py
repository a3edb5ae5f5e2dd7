"""The one declared schema of a stored run record, checked whenever the store is read.

:class:`RunRecord` (pydantic, strict) says what every record of ``store.sqlite`` holds: the run's
key, its provenance, its status and its metrics, with their types and ranges. Numbers are finite
and at most :data:`MAX_ABS_METRIC` in size (the store writes a metric that is not a number as
``null``, never as ``NaN`` or ``Infinity``), flags are booleans (``"no"`` or ``0`` is not a
collision flag), a status is ``ok`` or ``failed``, and a finished run (``ok``) carries the
metrics the leaderboard ranks by. :func:`check_record` adds what ties a record to its row: the key
of the record is the key of its row.
"""

from __future__ import annotations

import json
import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from benchmark.suite import KEY_COLUMNS, MAX_SEED, RunKey
from infra.limits import MAX_VEHICLES, MIN_VEHICLES

#: Metrics an ``ok`` run with at least one step must hold as finite numbers (not ``null``).
FINITE_WHEN_OK: tuple[str, ...] = (
    "reward", "tracking_reward", "energy_kwh", "power_mean_kw", "min_gap_m", "gap_mean_m",
    "gap_rmse_m", "speed_mean_mps",
)

#: Fields an ``ok`` run must hold (not ``null``).
REQUIRED_WHEN_OK: tuple[str, ...] = ("steps", "collision", "string_stable", "solver_failures")

#: The largest magnitude a stored metric may have: any real run's is far below it, and a mean
#: or an interval over millions of such values stays finite (1e308 would overflow to inf).
MAX_ABS_METRIC = 1e12

Metric = Annotated[float, Field(ge=-MAX_ABS_METRIC, le=MAX_ABS_METRIC)] | None
NonNegative = Metric  # each such field adds ge=0


class RunRecord(BaseModel):
    """A stored run record; fields not declared here are kept but not read by any command.

    Every number is finite; ``None`` stands for a metric that is undefined for the run (an
    empty percentile, a string gain of a still platoon), or a failed run's missing metrics.
    """

    model_config = ConfigDict(strict=True, allow_inf_nan=False, extra="allow", frozen=True)

    # the key
    id: str = Field(min_length=1)
    controller: str = Field(min_length=1)
    scenario: str = Field(min_length=1)
    n_vehicles: int = Field(ge=MIN_VEHICLES, le=MAX_VEHICLES)
    comm_delay_s: float = Field(ge=0.0)
    packet_loss: float = Field(ge=0.0, le=1.0)
    lag_s: float = Field(ge=0.0)
    seed: int = Field(ge=0, le=MAX_SEED)
    # the controller and the provenance
    name: str = Field(min_length=1)
    options: str
    family: str = Field(min_length=1)
    deterministic: bool | None = None
    version: str
    git_sha: str
    #: the learned policy's hash (marl.checkpoint.policy_id; empty: none, or stored before it)
    policy_sha256: str = Field(default="", pattern=r"^([0-9a-f]{64})?$")
    # the outcome
    status: Literal["ok", "failed"]
    error: str
    traceback: str | None = None
    wall_s: NonNegative = Field(default=None, ge=0.0)
    # the metrics (benchmark.metrics.run_metrics)
    steps: int | None = Field(default=None, ge=0)
    collision: bool | None = None
    string_stable: bool | None = None
    solver_failures: int | None = Field(default=None, ge=0)
    min_gap_m: Metric = None
    gap_mean_m: Metric = None
    gap_std_m: NonNegative = Field(default=None, ge=0.0)
    gap_rmse_m: NonNegative = Field(default=None, ge=0.0)
    speed_mean_mps: Metric = None
    speed_std_mps: NonNegative = Field(default=None, ge=0.0)
    speed_rmse_mps: NonNegative = Field(default=None, ge=0.0)
    accel_mean_mps2: Metric = None
    accel_std_mps2: NonNegative = Field(default=None, ge=0.0)
    accel_rms_mps2: NonNegative = Field(default=None, ge=0.0)
    jerk_rms_mps3: NonNegative = Field(default=None, ge=0.0)
    energy_kwh: Metric = None
    power_mean_kw: Metric = None
    energy_kwh_per_100km: Metric = None
    reward: Metric = None
    tracking_reward: Metric = None
    string_gain: NonNegative = Field(default=None, ge=0.0)
    spacing_string_gain: NonNegative = Field(default=None, ge=0.0)
    compute_ms_p50: NonNegative = Field(default=None, ge=0.0)
    compute_ms_p95: NonNegative = Field(default=None, ge=0.0)
    compute_ms_p99: NonNegative = Field(default=None, ge=0.0)
    compute_ms_first: NonNegative = Field(default=None, ge=0.0)
    comm_bits_per_s: NonNegative = Field(default=None, ge=0.0)
    # the safety filter (absent from stores written before it: read as 0 by runs.csv)
    safety_interventions: NonNegative = Field(default=None, ge=0.0, le=1.0)
    safety_correction_mps2: NonNegative = Field(default=None, ge=0.0)
    # the energy above steady cruise (absent from stores written before it: unknown, so runs.csv
    # leaves it empty; it cannot be recomputed without the trajectory)
    controllable_energy_kwh: Metric = None
    controllable_energy_kwh_per_100km: Metric = None
    # mixed traffic (benchmark.metrics.mixed_traffic_metrics; absent from stores written before
    # them: runs.csv leaves them empty, cav_share aside, which the scenario label gives)
    cav_share: NonNegative = Field(default=None, ge=0.0, le=1.0)
    head_to_tail_gain: NonNegative = Field(default=None, ge=0.0)
    speed_std_last_mps: NonNegative = Field(default=None, ge=0.0)
    speed_std_humans_mps: NonNegative = Field(default=None, ge=0.0)
    braking_events: int | None = Field(default=None, ge=0)
    braking_events_humans: int | None = Field(default=None, ge=0)
    braking_events_cavs: int | None = Field(default=None, ge=0)
    braking_events_per_veh_h: NonNegative = Field(default=None, ge=0.0)
    energy_humans_kwh: Metric = None
    energy_cavs_kwh: Metric = None
    controllable_energy_humans_kwh: Metric = None
    controllable_energy_cavs_kwh: Metric = None
    # the gap against the controller's own spacing policy, the jerk without the start-up
    # transient (absent from stores written before them: runs.csv leaves them empty)
    gap_rmse_own_policy_m: NonNegative = Field(default=None, ge=0.0)
    jerk_rms_after_start_mps3: NonNegative = Field(default=None, ge=0.0)
    # the controller's own constant time-gap policy r + h v (absent: it has none, or the run
    # was stored before it was recorded; controllers.base.SpacingPolicy)
    spacing_standstill_m: Metric = None
    spacing_time_gap_s: NonNegative = Field(default=None, ge=0.0)
    # energy per vehicle class (null: the class is not in the string, or no classes) and the
    # drag-saving model (benchmark.metrics.class_energy_metrics; absent from older stores)
    energy_kwh_per_100km_car: Metric = None
    energy_kwh_per_100km_i3: Metric = None
    energy_kwh_per_100km_van: Metric = None
    energy_kwh_per_100km_bus: Metric = None
    energy_kwh_per_100km_truck: Metric = None
    energy_drag_saving: str | None = None

    @field_validator("options")
    @classmethod
    def _options_are_a_json_object(cls, text: str) -> str:
        try:
            value = json.loads(text)
        except ValueError:
            raise ValueError("options must be a JSON object") from None
        if not isinstance(value, dict):
            raise ValueError("options must be a JSON object")
        return text

    @model_validator(mode="after")
    def _a_finished_run_has_its_metrics(self) -> RunRecord:
        if self.status != "ok":
            return self
        missing = [f for f in REQUIRED_WHEN_OK if getattr(self, f) is None]
        if self.steps:
            missing += [f for f in FINITE_WHEN_OK if getattr(self, f) is None]
        if missing:
            raise ValueError(f"a run with status 'ok' needs {', '.join(missing)}")
        return self


def _number_text(value: Any) -> str:
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def record_problem(run_id: str, status: str, record: Any) -> str | None:
    """What is wrong with the stored ``record`` of the row ``(run_id, status)``, or None.

    Checks the record against :class:`RunRecord`, then that its id, its status and its key
    (controller, scenario, N, V2V delay and loss, lag, seed) are those of its row.
    """
    if not isinstance(record, dict):
        return f"not a JSON object but {type(record).__name__}"
    try:
        rec = RunRecord.model_validate(record)
    except ValidationError as exc:
        parts = []
        for err in exc.errors()[:3]:
            where = ".".join(str(x) for x in err["loc"]) or "record"
            got = f" (got {_number_text(err['input'])})" if err["loc"] else ""
            parts.append(f"{where}: {err['msg'].rstrip('.')}{got}")
        more = len(exc.errors()) - 3
        return "; ".join(parts) + (f"; and {more} more" if more > 0 else "")
    if rec.id != run_id:
        return f"its id {rec.id!r} is not its row's"
    key_id = RunKey(**{k: getattr(rec, k) for k in KEY_COLUMNS}).id
    if key_id != run_id:
        return f"its key (controller, scenario, N, settings, seed) reads {key_id!r}, not its row's"
    if rec.status != status:
        return f"its status {rec.status!r} is not its row's {status!r}"
    return None
