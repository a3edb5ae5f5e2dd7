"""SUMO road networks of a batch: one straight single-lane road per episode, or one ring per
episode, written as plain XML and built by the wheel's ``netconvert``.

The episodes of a batch share one SUMO simulation (libsumo runs one per process) on roads that
never meet, so each episode evolves as it would alone. Internal junction lanes are left out
(``--no-internal-links``), so the distance along a ring is exactly the sum of its edges' lengths
(each edge's ``length`` is set, not measured from its drawn shape).
"""

from __future__ import annotations

import atexit
import math
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

#: Edges of one ring (quarter circles).
RING_EDGES = 4
#: Lateral distance between the roads of a batch (m): they never interact in SUMO anyway.
ROAD_SPACING_M = 50.0

_folder: Path | None = None
_built: dict[tuple[str, int, float, float], Path] = {}


def sumo_home() -> str:
    """The folder of the ``sumo`` wheel (its ``bin`` holds ``netconvert``); also set as
    ``SUMO_HOME`` for the tools, which read it."""
    import sumo

    home = str(sumo.SUMO_HOME)
    os.environ.setdefault("SUMO_HOME", home)
    return home


def tool(name: str) -> str:
    """The path of one of the wheel's binaries (``netconvert``, ``emissionsDrivingCycle``)."""
    return str(Path(sumo_home()) / "bin" / name)


def run_tool(name: str, args: list[str], out: Path) -> None:
    """Run the wheel's binary ``name`` with ``args``, which writes ``out``.

    Raises
    ------
    RuntimeError
        When it fails or writes no ``out`` (the end of its error output is in the message).
    """
    done = subprocess.run([tool(name), *args], capture_output=True, text=True, check=False)
    if done.returncode != 0 or not out.exists():
        raise RuntimeError(f"{name} failed ({done.returncode}): {done.stderr.strip()[-500:]}")


def work_folder() -> Path:
    """This process's scratch folder for networks and route files (removed at exit)."""
    global _folder
    if _folder is None:
        _folder = Path(tempfile.mkdtemp(prefix="cacc-bench-sumo-"))
        atexit.register(shutil.rmtree, _folder, True)
    return _folder


def road_edge(k: int) -> str:
    """The edge id of episode ``k``'s straight road."""
    return f"r{k}"


def ring_edges(k: int) -> list[str]:
    """The edge ids of episode ``k``'s ring, in driving order."""
    return [f"q{k}_{j}" for j in range(RING_EDGES)]


def network(kind: str, roads: int, length_m: float, speed_limit_mps: float) -> Path:
    """The ``.net.xml`` of ``roads`` straight roads or rings (``kind`` ``road`` or ``ring``) of
    ``length_m`` each with the speed limit ``speed_limit_mps``, built once per process.

    Raises
    ------
    RuntimeError
        When ``netconvert`` fails (its output is in the message).
    """
    key = (kind, roads, float(length_m), float(speed_limit_mps))
    if key in _built:
        return _built[key]
    folder = work_folder()
    stem = folder / f"{kind}_{roads}_{len(_built)}"
    nodes, edges = [], []
    for k in range(roads):
        y = k * ROAD_SPACING_M  # the straight roads' lateral offset
        if kind == "road":
            nodes += [f'<node id="a{k}" x="0" y="{y}"/>',
                      f'<node id="b{k}" x="{length_m!r}" y="{y}"/>']
            edges.append(f'<edge id="{road_edge(k)}" from="a{k}" to="b{k}" numLanes="1" '
                         f'speed="{speed_limit_mps!r}" length="{length_m!r}"/>')
        else:
            radius = length_m / (2 * math.pi)
            cx, cy = 0.0, k * (2 * radius + ROAD_SPACING_M)
            ids = ring_edges(k)
            for j in range(RING_EDGES):  # a quarter circle from node j, which is its start
                arc = [(cx + radius * math.cos(2 * math.pi * (j + f / 8) / RING_EDGES),
                        cy + radius * math.sin(2 * math.pi * (j + f / 8) / RING_EDGES))
                       for f in range(9)]
                nodes.append(f'<node id="n{k}_{j}" x="{arc[0][0]!r}" y="{arc[0][1]!r}"/>')
                shape = " ".join(f"{x!r},{yy!r}" for x, yy in arc)
                edges.append(f'<edge id="{ids[j]}" from="n{k}_{j}" to="n{k}_{(j + 1) % RING_EDGES}" '
                             f'numLanes="1" speed="{speed_limit_mps!r}" '
                             f'length="{length_m / RING_EDGES!r}" shape="{shape}"/>')
    nod, edg, net = (stem.with_suffix(s) for s in (".nod.xml", ".edg.xml", ".net.xml"))
    nod.write_text("<nodes>\n" + "\n".join(nodes) + "\n</nodes>\n")
    edg.write_text("<edges>\n" + "\n".join(edges) + "\n</edges>\n")
    run_tool("netconvert", ["--node-files", str(nod), "--edge-files", str(edg), "-o", str(net),
                            "--no-turnarounds", "true", "--no-internal-links", "true",
                            "--no-warnings", "true"], net)
    _built[key] = net
    return net
