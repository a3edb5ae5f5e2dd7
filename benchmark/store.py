"""The results store: an embedded SQLite file, one committed transaction per finished batch.

It is the source of truth of a results folder: the CSV files are rebuilt from it, a killed sweep
loses only the runs in flight (a batch is stored as a whole when it finishes), and ``--resume``
skips what is stored. A writer holds the folder's lock (``store.lock``, via ``filelock``) for as
long as the store is open, so two commands never write one folder; the holder's pid and command
are in ``store.owner``. Opening checks the file's integrity (SQLite ``quick_check``) and that it
is a cacc-bench store (its tables and schema version; another program's SQLite file is refused
and never written into); reading checks every record against the one declared schema
(:mod:`benchmark.record_schema`).
"""

from __future__ import annotations

import io
import json
import math
import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmark.folder_lock import LOCK_NAME, OWNER_NAME, holder, write_owner
from infra.errors import ConfigError

STORE_NAME = "store.sqlite"
#: 2: controller labels leave out options given at their default value (1 kept them); a
#: version-1 store is relabelled when opened.
SCHEMA_VERSION = 2

_SCHEMA = f"""
BEGIN;
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE runs (
    id TEXT PRIMARY KEY,
    status TEXT NOT NULL,
    record TEXT NOT NULL,
    finished_at REAL NOT NULL
);
CREATE TABLE trajectories (id TEXT PRIMARY KEY, data BLOB NOT NULL);
INSERT INTO meta (key, value) VALUES ('schema_version', '{SCHEMA_VERSION}');
COMMIT;
"""

#: The tables of a store and their columns; a file with other tables is not a store.
_TABLES: dict[str, tuple[str, ...]] = {
    "meta": ("key", "value"),
    "runs": ("id", "status", "record", "finished_at"),
    "trajectories": ("id", "data"),
}


def _not_a_store(conn: sqlite3.Connection) -> str | None:
    """Why the SQLite database of ``conn`` is not a cacc-bench store, or None (read only)."""
    tables = {name: tuple(c[1] for c in conn.execute(f'PRAGMA table_info("{name}")'))
              for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' "
                                          "AND name NOT LIKE 'sqlite_%'")}
    if tables != _TABLES:
        listed = ", ".join(sorted(tables)) or "none"
        return f"its tables ({listed}) are not those of a cacc-bench store"
    row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
    if row is None:
        return "it has no schema_version"
    return None


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _clean(value.item())
    return value


#: SQLite's errors of the place a store lies in, not of the file: no room, no permission.
_NO_ROOM = ("SQLITE_FULL", "SQLITE_IOERR_WRITE")
_NO_ACCESS = ("SQLITE_READONLY", "SQLITE_CANTOPEN", "SQLITE_PERM", "SQLITE_AUTH", "SQLITE_IOERR")


def _open_failure(path: Path, exc: Exception) -> Exception:
    """What opening the store ``path`` failing with ``exc`` tells the user, in one line: a full
    disk (``exc`` itself, which the command line reports as such), no access, or a damaged file
    (only then: move it away)."""
    name = getattr(exc, "sqlite_errorname", None) or ""
    if name in _NO_ROOM:
        return exc
    if name.startswith(_NO_ACCESS):
        return ConfigError(f"{path} cannot be opened or written ({exc}); make {path.parent} "
                           "writable (and its disk reachable), or choose another --out")
    reason = " ".join(str(exc).split())
    return ConfigError(f"{path} is not a readable results store ({reason}); the CSV files beside "
                       "it are left as they are: move the file away and rerun the sweep into "
                       "this folder, or choose another --out")


def _remedy(path: Path, run_id: str) -> str:
    """What to do about an invalid row: delete it and rerun it with ``--resume``."""
    quoted = run_id.replace("'", "''")
    return (f"delete that row (sqlite3 {path} \"DELETE FROM runs WHERE id = '{quoted}'\") and "
            "rerun the sweep with --resume to run it again, or choose another --out")


class ResultStore:
    """SQLite store of finished runs in ``folder/store.sqlite``."""

    def __init__(self, folder: Path | str, create: bool = True, writer: bool = False) -> None:
        self.folder = Path(folder)
        self.path = self.folder / STORE_NAME
        self._lock: Any = None
        if not create and not self.path.exists():
            raise ConfigError(
                f"no results store in {self.folder} (expected {self.path}); "
                "run `cacc-bench run --out DIR` first"
            )
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"cannot make the results folder {self.folder} ({exc.strerror}); "
                              "choose a writable --out") from None
        if writer:
            # the lock first: a racing writer's new file is 0 bytes until its schema is written
            self._acquire()
        if self.path.exists() and self.path.stat().st_size == 0:
            self._release()
            raise ConfigError(
                f"{self.path} is empty (0 bytes), not a results store; remove it to start a new "
                "store in this folder, or choose another --out"
            )
        new = not self.path.exists()
        foreign = None
        try:
            self.conn = sqlite3.connect(self.path, timeout=30)
            if new:  # tables and schema version in one transaction
                try:
                    self.conn.executescript(_SCHEMA)
                except BaseException:  # an interrupt leaves no half-made (0-byte) store
                    self.conn.close()
                    self.path.unlink(missing_ok=True)
                    raise
            check = [ln for (row,) in self.conn.execute("PRAGMA quick_check")
                     for ln in str(row).splitlines() if not ln.startswith("***")]
            if check != ["ok"]:
                more = f"; {len(check) - 1} more problems" if len(check) > 1 else ""
                raise sqlite3.DatabaseError(f"integrity check: {(check or ['no answer'])[0]}{more}")
            foreign = _not_a_store(self.conn)
            version = None if foreign else self.get_meta("schema_version")
        except (sqlite3.DatabaseError, ValueError) as exc:
            self._close_quietly()
            raise _open_failure(self.path, exc) from None
        if foreign is not None:
            self._close_quietly()
            raise ConfigError(
                f"{self.path} is an SQLite file but not a cacc-bench results store ({foreign}); "
                "nothing was written to it: move it away, or choose another --out"
            )
        if version == 1:
            self._relabel_v1()
        elif version != SCHEMA_VERSION:
            self.close()
            raise ConfigError(
                f"{self.path} has store schema {version!r}, this cacc-bench reads "
                f"{SCHEMA_VERSION}; choose another --out"
            )

    def _relabel_v1(self) -> None:
        """Upgrade a version-1 store: relabel runs whose label holds options at their default
        (``ovm[alpha=0.5]`` -> ``ovm``), so a resumed sweep neither reruns nor duplicates them;
        of two runs that become one, the later finished is kept."""
        from benchmark.suite import KEY_COLUMNS, RunKey
        from controllers.registry import canonical_options, controller_label
        from infra.errors import CaccBenchError

        rows = self.conn.execute(
            "SELECT id, status, record, finished_at FROM runs ORDER BY finished_at").fetchall()
        with self.conn:
            for run_id, status, text, finished in rows:
                try:
                    rec = json.loads(text)
                    canon = canonical_options(rec["name"], json.loads(rec["options"]))
                except (ValueError, KeyError, TypeError, CaccBenchError):
                    continue  # unreadable or unregistered: left for records() to judge
                label = controller_label(rec["name"], canon)
                if label == rec["controller"]:
                    continue
                rec.update(controller=label, options=json.dumps(canon, sort_keys=True))
                rec["id"] = new_id = RunKey(**{k: rec[k] for k in KEY_COLUMNS}).id
                self.conn.execute("DELETE FROM runs WHERE id = ?", (run_id,))
                kept = self.conn.execute("SELECT finished_at FROM runs WHERE id = ?",
                                         (new_id,)).fetchone()
                if kept is not None and kept[0] > finished:
                    self.conn.execute("DELETE FROM trajectories WHERE id = ?", (run_id,))
                    continue
                self.conn.execute(
                    "INSERT OR REPLACE INTO runs (id, status, record, finished_at) "
                    "VALUES (?, ?, ?, ?)", (new_id, status, json.dumps(rec, sort_keys=True),
                                            finished))
                self.conn.execute("UPDATE OR REPLACE trajectories SET id = ? WHERE id = ?",
                                  (new_id, run_id))
            self.conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
                              ("schema_version", json.dumps(SCHEMA_VERSION)))

    def _acquire(self) -> None:
        """Take the folder's writer lock, or refuse naming the process that holds it; a store
        that is a link into another folder is refused (that folder's lock is not this one)."""
        from filelock import FileLock, Timeout

        if self.path.is_symlink():
            home = self.path.resolve().parent
            raise ConfigError(f"{self.path} is a link into {home}, whose writers hold that "
                              f"folder's lock, not this one's; write it there (--out {home}), or "
                              "replace the link with a copy of the store")
        if (self.folder / LOCK_NAME).is_dir():
            raise ConfigError(f"{self.folder / LOCK_NAME} is a folder, so {self.folder} cannot be "
                              "locked; remove it or choose another --out")
        lock = FileLock(self.folder / LOCK_NAME, timeout=0)
        try:
            lock.acquire()
            self._lock = lock
            write_owner(self.folder)
        except PermissionError as exc:  # a read-only folder, or lock files of another user
            if self._lock is not None:
                self._lock.release()
                self._lock = None
            raise ConfigError(f"{self.folder} cannot be locked for writing ({exc.strerror}); "
                              "make it writable, or copy it and work on the copy") from None
        except Timeout:
            who = holder(self.folder)
            raise ConfigError(
                f"{self.folder} is being written by {who}; wait for it to finish, or choose "
                "another --out"
            ) from None

    def _release(self) -> None:
        if self._lock is not None:
            (self.folder / OWNER_NAME).unlink(missing_ok=True)
            self._lock.release()
            self._lock = None

    def close(self) -> None:
        """Close the connection and release the writer lock."""
        self.conn.close()
        self._release()

    def _close_quietly(self) -> None:
        conn = getattr(self, "conn", None)
        if conn is not None:
            conn.close()
        self._release()

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ meta
    def get_meta(self, key: str) -> Any:
        """A JSON value stored under ``key`` (None if absent)."""
        row = self.conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else json.loads(row[0])

    def set_meta(self, key: str, value: Any) -> None:
        """Store a JSON value under ``key`` (committed)."""
        with self.conn:
            self.conn.execute(
                "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, json.dumps(value))
            )

    # ------------------------------------------------------------------ runs
    def add(self, record: dict[str, Any], trajectory: dict[str, np.ndarray] | None = None) -> None:
        """Store one finished run (and optionally its trajectory) in one committed transaction.

        A run stored again (a failed run retried by ``--resume``) replaces the old row.
        """
        self.add_batch([(record, trajectory)])

    def add_batch(self, runs: list[tuple[dict[str, Any], dict[str, np.ndarray] | None]]) -> None:
        """Store the finished runs of one batch, each with an optional trajectory, in one
        committed transaction (all or none of them: a batch finishes as a whole)."""
        rows, blobs = [], []
        now = time.time()
        for record, trajectory in runs:
            rec = {k: _clean(v) for k, v in record.items() if not k.startswith("_")}
            rows.append((rec["id"], rec["status"], json.dumps(rec, sort_keys=True), now))
            if trajectory is not None:
                buf = io.BytesIO()
                np.savez_compressed(buf, **trajectory)  # type: ignore[arg-type]
                blobs.append((rec["id"], buf.getvalue()))
        with self.conn:
            self.conn.executemany(
                "INSERT OR REPLACE INTO runs (id, status, record, finished_at) VALUES (?, ?, ?, ?)",
                rows)
            self.conn.executemany("INSERT OR REPLACE INTO trajectories (id, data) VALUES (?, ?)",
                                  blobs)

    def ids(self, status: str | None = None) -> set[str]:
        """Ids of stored runs (optionally only those with ``status``)."""
        if status is None:
            rows = self.conn.execute("SELECT id FROM runs").fetchall()
        else:
            rows = self.conn.execute("SELECT id FROM runs WHERE status = ?", (status,)).fetchall()
        return {r[0] for r in rows}

    def records(self) -> list[dict[str, Any]]:
        """All stored run records (a consistent snapshot: one read transaction), each checked
        against :class:`benchmark.record_schema.RunRecord` and its row.

        Raises
        ------
        ConfigError
            Naming the first row whose record is unreadable or invalid, and what to do.
        """
        from benchmark.record_schema import record_problem

        out = []
        try:
            rows = self.conn.execute("SELECT id, status, record FROM runs ORDER BY id").fetchall()
        except sqlite3.DatabaseError as exc:
            raise ConfigError(f"{self.path}: the runs table cannot be read ({exc}); move the "
                              "file away and rerun the sweep, or choose another --out") from None
        for run_id, status, text in rows:
            try:
                if not isinstance(run_id, str) or not isinstance(text, str | bytes):
                    raise ValueError("not the record of a run")
                rec = json.loads(text)
                if not isinstance(rec, dict) or rec.get("id") != run_id:
                    raise ValueError("not the record of this run")
            except ValueError as exc:
                raise ConfigError(
                    f"{self.path}: the stored record of run {run_id!r} is unreadable ({exc}); "
                    f"the CSV files are left as they are: {_remedy(self.path, run_id)}"
                ) from None
            problem = record_problem(run_id, status, rec)
            if problem is not None:
                raise ConfigError(
                    f"{self.path}: the stored record of run {run_id!r} is invalid ({problem}); "
                    f"the CSV files are left as they are: {_remedy(self.path, run_id)}"
                )
            out.append(rec)
        return out

    def trajectory(self, run_id: str) -> dict[str, np.ndarray] | None:
        """The stored trajectory arrays of a run, if any."""
        row = self.conn.execute(
            "SELECT data FROM trajectories WHERE id = ?", (run_id,)
        ).fetchone()
        if row is None:
            return None
        try:
            with np.load(io.BytesIO(row[0]), allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
        except Exception as exc:  # any damage of the blob (zip, header, type) is the same
            raise ConfigError(
                f"{self.path}: the stored trajectory of run {run_id!r} is unreadable "
                f"({type(exc).__name__}: {exc}); delete it (`DELETE FROM trajectories WHERE id = "
                f"'{run_id}'`) or rerun that run into another --out"
            ) from None

    def trajectory_ids(self) -> set[str]:
        """Ids of runs with a stored trajectory."""
        return {r[0] for r in self.conn.execute("SELECT id FROM trajectories")}
