"""``cacc-bench list``: scenarios and controllers (with family and V2V needs)."""

from __future__ import annotations

import argparse

from benchmark.cli import plain
from controllers.registry import CONTROLLERS, controller_options
from envs.scenarios import list_scenarios


def main(argv: list[str]) -> int:
    """Print the registered scenarios and controllers."""
    p = argparse.ArgumentParser(prog="cacc-bench list", description=plain(__doc__))
    p.parse_args(argv)
    print("scenarios (id: targets d*, v*; length; description):")
    for s in list_scenarios():
        opts = ", ".join(f"{k}={v}" for k, v in s.defaults.items())
        extra = f" [options: {opts}]" if opts else ""
        pub = " (published)" if s.published else ""
        print(f"  {s.id:<14} d*={s.target_gap_m:g} m, v*={s.target_speed_mps:g} m/s, "
              f"{s.n_steps} steps, N={s.default_vehicles} by default{pub}: {s.description}{extra}")
    print("\ncontrollers (name [family]: description; V2V; options with their defaults, set as "
          "name:key=value):")
    for c in CONTROLLERS.values():
        if not c.available:
            print(f"  {c.name:<8} [{c.family}] {c.description}  (not available in this version)")
            continue
        print(f"  {c.name:<8} [{c.family}] {c.description}; V2V: {c.v2v}")
        opts = ", ".join(f"{k}={v}" for k, v in controller_options(c.name).items())
        print(f"           options: {opts or 'none'}")
    return 0
