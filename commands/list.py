"""``cacc-bench list``: scenarios and controllers (with family and V2V needs)."""

from __future__ import annotations

import argparse

from commands.cli import plain
from controllers.registry import CONTROLLERS, controller_options
from envs.params import PlatoonParams
from envs.scenarios import ARRANGEMENT_DEFAULTS, list_scenarios


def main(argv: list[str]) -> int:
    """Print the registered scenarios and controllers."""
    parser = argparse.ArgumentParser(prog="cacc-bench list", description=plain(__doc__))
    parser.parse_args(argv)
    print("scenarios (id: targets d*, v*; length; description):")
    for s in list_scenarios():
        opts = ", ".join(f"{k}={v}" for k, v in s.defaults.items())
        extra = f" [options: {opts}]" if opts else ""
        pub = " (published)" if s.published else ""
        print(f"  {s.id:<14} d*={s.target_gap_m:g} m, v*={s.target_speed_mps:g} m/s, "
              f"{s.n_steps} steps, N={s.default_vehicles} by default{pub}: {s.description}{extra}")
    opts = ", ".join(f"{k}={v!s}" if v != "" else f"{k}=" for k, v in ARRANGEMENT_DEFAULTS.items())
    print(f"  every scenario also takes the arrangement of human drivers (mixed traffic; "
          f"docs/concepts/mixed-traffic.md): {opts}")
    print("\naction modes of the learning interface (envs.accel_mode; Gymnasium ids "
          "cacc_bench/<scenario> and cacc_bench_accel/<scenario>):")
    print("  ovm-gain   Discrete(4) per follower: the published OVM gains (alpha, beta); "
          "15 observed numbers (own, front, rear blocks)")
    p = PlatoonParams()
    print(f"  accel      Box({p.accel_min_mps2:g}, {p.accel_max_mps2:g}) m/s^2 per follower, the MPC's input bounds; 12 observed "
          "numbers: own sensed state, actuator state, V2V (predecessor's command, leader's "
          "acceleration and speed) through the run's delay and loss, position")
    print("\ncontrollers (name [family]: description; V2V; options with their defaults, set as "
          "name:key=value):")
    for c in CONTROLLERS.values():
        if not c.available:
            print(f"  {c.name:<8} [{c.family}] {c.description}  (not available in this version)")
            continue
        print(f"  {c.name:<8} [{c.family}] {c.description}; V2V: {c.v2v}")
        opts = ", ".join(f"{k}={v}" for k, v in controller_options(c.name).items())
        print(f"           options: {opts or 'none'}")
    print("  safe:<name> [its family] the controller <name> (any above but openacc-real) behind "
          "the worst-case-braking safety filter (docs/safety-filter.md), e.g. safe:cacc, "
          "safe:bdc:scenario=catchup-v1")
    from controllers.safety_filter import OPTION_PREFIX, SafetyFilterConfig

    own = ", ".join(f"{OPTION_PREFIX}{k}={getattr(SafetyFilterConfig(), k)}"
                    for k in SafetyFilterConfig.__dataclass_fields__)
    print(f"           options: <name>'s, and {own}")
    return 0
