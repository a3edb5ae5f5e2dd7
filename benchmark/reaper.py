"""A watchdog that ends the processes a command leaves behind, whatever ended the command.

``python -m benchmark.reaper PID`` watches process ``PID`` (the command that starts a local Ray
instance) through its standard input: while the pipe is open it notes every descendant of
``PID`` (Ray's GCS, raylet, its agents and workers), and when the pipe closes (the command
exited, or was killed, SIGKILL included) it kills those still alive, then exits. A command
that ends at once on a signal first writes its descendants to the pipe (:func:`hand_over`, lines
``PID START``): Ray kills its raylet when the command dies, and the agents the raylet started
since the last scan would otherwise be orphans nobody noted. Ray's own
shutdown misses its agents when the driver is killed (``ray::DashboardAgent`` and
``ray::RuntimeEnvAgent`` stayed alive). Linux only (``/proc``); only the standard library, so
it starts in a few tens of milliseconds.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import time
from pathlib import Path

#: Seconds between two scans of the watched process's descendants.
SCAN_S = 0.1


def _stat(pid: int) -> tuple[int, str, str] | None:
    """``(ppid, state, start time)`` of ``pid`` from ``/proc`` (None if it is gone)."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
        fields = text[text.rindex(")") + 2:].split()
        return int(fields[1]), fields[0], fields[19]
    except (OSError, ValueError, IndexError):  # gone, or read while it was ending
        return None


def descendants(root: int) -> dict[int, str]:
    """Every living descendant of ``root``: pid -> start time (to tell a reused pid apart)."""
    children: dict[int, list[int]] = {}
    start: dict[int, str] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        info = _stat(int(entry))
        if info is None or info[1] == "Z":
            continue
        children.setdefault(info[0], []).append(int(entry))
        start[int(entry)] = info[2]
    out: dict[int, str] = {}
    todo = list(children.get(root, []))
    while todo:
        pid = todo.pop()
        if pid in out or pid == os.getpid():
            continue
        out[pid] = start[pid]
        todo += children.get(pid, [])
    return out


def kill_all(seen: dict[int, str]) -> None:
    """SIGKILL every process of ``seen`` that is still the one noted (same start time)."""
    for pid, started in seen.items():
        info = _stat(pid)
        if info is not None and info[1] != "Z" and info[2] == started:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass


def hand_over(fd: int, root: int) -> None:
    """Write ``root``'s living descendants to the reaper's pipe ``fd`` (one ``PID START`` line
    each), for it to end them with the rest."""
    data = "".join(f"{pid} {start}\n" for pid, start in descendants(root).items())
    os.write(fd, data.encode())


def _parse(lines: bytes) -> dict[int, str]:
    """The ``PID START`` lines of :func:`hand_over` (malformed lines and this process left out)."""
    out = {}
    for line in lines.decode(errors="replace").splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[0].isdigit() and parts[1].isdigit() \
                and int(parts[0]) != os.getpid():
            out[int(parts[0])] = parts[1]
    return out


def main(argv: list[str]) -> int:
    """Watch ``argv[0]`` (a pid) until standard input closes, then kill what it left."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C to the group must not stop it
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    root = int(argv[0])
    # not the command's to end: they ran before Ray. Told by start time (clock ticks, no later
    # than this reaper's), not by this first scan, which a loaded machine can delay until
    # Ray's processes are up
    own = _stat(os.getpid())
    assert own is not None
    before = {(p, t) for p, t in descendants(root).items() if int(t) <= int(own[2])}
    seen: dict[int, str] = {}
    stdin = sys.stdin.buffer
    pending = b""
    while True:
        seen.update(descendants(root))
        ready, _, _ = select.select([stdin], [], [], SCAN_S)
        if ready:
            chunk = os.read(stdin.fileno(), 65536)
            if not chunk:
                break
            complete, _, pending = (pending + chunk).rpartition(b"\n")
            seen.update(_parse(complete))
    time.sleep(0.2)  # what the command's own shutdown ends by itself is gone by now
    for _ in range(3):  # the command's processes, reparented when it died, may have started more
        alive = [p for p, t in seen.items() if (_stat(p) or (0, "", ""))[2] == t]
        for pid in [root, *alive]:  # only the processes noted, not a reused pid
            seen.update(descendants(pid))
        kill_all({pid: t for pid, t in seen.items() if (pid, t) not in before})
        time.sleep(SCAN_S)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
