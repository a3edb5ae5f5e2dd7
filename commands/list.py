"""``cacc-bench list``: scenarios and controllers (with family and V2V needs), the built-in ones
and those of installed packages (entry points ``cacc_bench.controllers``, ``cacc_bench.scenarios``)."""

from __future__ import annotations

from commands.cli import command_parser
from controllers.registry import (
    CONTROLLERS,
    ENTRY_POINT_GROUP,
    controller_options,
    plugin_conflicts,
    plugin_targets,
    resolve,
)
from envs.params import PlatoonParams
from envs.scenarios import ARRANGEMENT_DEFAULTS, list_scenarios, scenario_spec
from envs.scenarios import ENTRY_POINT_GROUP as SCENARIO_GROUP
from envs.scenarios import plugin_targets as scenario_targets
from infra.errors import CaccBenchError


def main(argv: list[str]) -> int:
    """Print the registered scenarios and controllers."""
    command_parser("list", __doc__).parse_args(argv)
    print("scenarios (id: targets d*, v*; length; description):")
    for s in list_scenarios():
        opts = ", ".join(f"{k}={v}" for k, v in s.defaults.items())
        extra = f" [options: {opts}]" if opts else ""
        pub = " (published)" if s.published else ""
        print(f"  {s.id:<14} d*={s.target_gap_m:g} m, v*={s.target_speed_mps:g} m/s, "
              f"{s.n_steps} steps, N={s.default_vehicles} by default{pub}: {s.description}{extra}")
    listed = {s.id for s in list_scenarios()}
    for name, target in scenario_targets().items():
        if name not in listed:  # an installed package's scenario that does not load: why
            try:
                scenario_spec(name)
            except CaccBenchError as exc:
                print(f"  {name:<14} ({SCENARIO_GROUP} entry point {target}) cannot be used: {exc}")
    print("  package.module:NAME  a ScenarioSpec of your own (docs/contributing.md, Add a "
          "scenario), e.g. --scenarios my_scenarios:HILL")
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
        if not c.available:  # an extra not installed says how to install it
            why = (f"needs {', '.join(c.requires)}; install it with: {c.install}" if c.install
                   else "not available in this version")
            print(f"  {c.name:<8} [{c.family}] {c.description}  ({why})")
            continue
        print(f"  {c.name:<8} [{c.family}] {c.description}; V2V: {c.v2v}")
        opts = ", ".join(f"{k}={v}" for k, v in controller_options(c.name).items())
        print(f"           options: {opts or 'none'}")
    for name, target in plugin_targets().items():  # installed packages' controllers
        try:
            c = resolve(name)
            opts = ", ".join(f"{k}={v}" for k, v in controller_options(name).items())
        except CaccBenchError as exc:
            print(f"  {name:<8} ({ENTRY_POINT_GROUP} entry point {target}) cannot be used: {exc}")
            continue
        print(f"  {c.name:<8} [{c.family}] {c.description} (installed: {target}); V2V: {c.v2v}")
        print(f"           options: {opts or 'none'}")
    for name, why in plugin_conflicts().items():
        print(f"  {name:<8} ({ENTRY_POINT_GROUP} entry point) {why}")
    print("  package.module:Class  a controller class of your own, a subclass of "
          "controllers.base.Controller (docs/contributing.md, Add a controller), e.g. "
          "--controllers my_laws:MyLaw:gain=2 (options after a further colon)")
    print("  safe:<name> [its family] the controller <name> (any above but openacc-real) behind "
          "the worst-case-braking safety filter (docs/safety-filter.md), e.g. safe:cacc, "
          "safe:bdc:scenario=catchup-v1")
    from controllers.safety_filter import OPTION_PREFIX, SafetyFilterConfig

    own = ", ".join(f"{OPTION_PREFIX}{k}={getattr(SafetyFilterConfig(), k)}"
                    for k in SafetyFilterConfig.__dataclass_fields__)
    print(f"           options: <name>'s, and {own}")
    return 0
