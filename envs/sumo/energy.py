"""SUMO's MMPEVEM electric-vehicle energy model (Koch et al., ITSC 2021) on given speeds and
accelerations, through the wheel's ``emissionsDrivingCycle`` and its BMW i3 vehicle type
(``data/emissions/MMPEVEM/BMW_i3.xml``: the same vehicle parameters and loss map as the
project's energy model, ``envs/data/energy/SOURCE.md``).

``emissionsDrivingCycle`` computes one value per line of a time line, the battery's energy rate
in Wh per second; MMPEVEM keeps no state from one line to the next, so every vehicle-step of a
batch goes into one time line (one process).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from envs.sumo.network import run_tool, sumo_home, work_folder

#: The wheel's MMPEVEM vehicle type of the BMW i3, and its id.
I3_VTYPE_FILE = Path("data") / "emissions" / "MMPEVEM" / "BMW_i3.xml"
I3_VTYPE = "BMW_i3"


def mmpevem_power_kw(speed_mps: np.ndarray, accel_mps2: np.ndarray) -> np.ndarray:
    """Battery power (kW, negative when recuperating) of SUMO's MMPEVEM BMW i3 at each
    ``(speed, acceleration)`` (arrays of one shape), flat road.

    Raises
    ------
    RuntimeError
        When ``emissionsDrivingCycle`` fails (its output is in the message).
    """
    from envs.sumo import require_sumo

    require_sumo()
    v = np.asarray(speed_mps, dtype=np.float64)
    a = np.asarray(accel_mps2, dtype=np.float64)
    folder = work_folder()
    cycle, out = folder / "cycle.csv", folder / "cycle.out.csv"
    lines = [f"{k};{float(vk)!r};{float(ak)!r}" for k, (vk, ak) in
             enumerate(zip(v.ravel(), a.ravel(), strict=True))]
    cycle.write_text("\n".join(lines) + "\n")
    run_tool("emissionsDrivingCycle", ["-t", str(cycle), "--additional-files",
                                       str(Path(sumo_home()) / I3_VTYPE_FILE), "--vtype", I3_VTYPE,
                                       "-e", "MMPEVEM", "-o", str(out)], out)
    rows = [r.split(";") for r in out.read_text().splitlines() if r.strip()]
    if len(rows) != v.size:
        raise RuntimeError(f"emissionsDrivingCycle wrote {len(rows)} lines for {v.size}")
    wh_per_s = np.array([float(r[-1]) for r in rows])
    return (wh_per_s * 3.6).reshape(v.shape)
