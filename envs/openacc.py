"""OpenACC real-world replay data: read, validate and window the JRC OpenACC files.

The three benchmark windows (scenarios ``openacc-s-v1``, ``openacc-m-v1``, ``openacc-l-v1``)
replay the leader speed of a ZalaZONE dynamic-platform platoon experiment from the JRC OpenACC
database (Makridis et al. 2021, Transportation Research Part C 125, 103047; CC BY 4.0,
(c) European Union). The package ships trimmed copies of the original files in
``envs/data/openacc/`` (see the ``SOURCE.md`` there); nothing here reads anything else.

File format (all OpenACC campaigns): 5 metadata lines (``Date``, ``Vehicle_order``,
``Number_of_vehicles``, ``ACC``, ``Distance_setting``), one column-name line, then 10 Hz rows.
Columns are selected by name: ``Time`` [s], ``Speed{i}`` [m/s] (vehicle i, 1 = leader) and
``IVS{i}`` [m], the bumper-to-bumper gap between vehicle i and vehicle i + 1, so follower k
(vehicle k + 1) has the gap ``IVS{k}`` to its predecessor.

Acceleration is not in the data. It is the plain central difference of the speed,
``np.gradient(v, 0.1)``, with **no smoothing** (the JRC speeds are already B-spline
interpolated to 10 Hz and smooth). It is computed over the whole shipped file (window plus a 5 s
margin on each side), so the window's first and last samples are central differences too.

pandas is imported inside the functions that need it, so importing this module is cheap.
"""

from __future__ import annotations

import functools
import importlib.resources
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from infra.errors import CaccBenchError, ConfigError, UnknownNameError

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "DT_S",
    "MAX_NAN_RUN_ROWS",
    "OpenACCDataError",
    "OpenACCHeader",
    "OpenACCWindow",
    "OpenACCWindowSpec",
    "RealFollowersRecord",
    "WINDOWS",
    "data_path",
    "load_window",
    "read_openacc_csv",
    "read_openacc_header",
    "real_followers_record",
]

#: Sample time of the OpenACC data [s] (10 Hz), the same as the environment step.
DT_S: float = 0.1
#: Longest run of consecutive NaN rows in one column that is filled by interpolation
#: (20 rows = 2 s); a longer run is an error.
MAX_NAN_RUN_ROWS: int = 20
#: Largest allowed deviation of a time step from ``DT_S`` [s].
DT_TOL_S: float = 0.01
#: Tolerance when picking the sample at a given time [s].
TIME_MATCH_TOL_S: float = 0.01
#: Number of metadata lines before the column-name line.
N_METADATA_LINES: int = 5

_HEADER_KEYS: tuple[str, ...] = ("Date", "Vehicle_order", "Number_of_vehicles", "ACC",
                                  "Distance_setting")


class OpenACCDataError(CaccBenchError, ValueError):
    """An OpenACC file is missing or malformed; the message names the file and the problem."""


@dataclass(frozen=True)
class OpenACCWindowSpec:
    """Description of one benchmark replay window.

    Attributes
    ----------
    name : str
        Window name, ``"S"``, ``"M"`` or ``"L"`` (the ACC distance setting of the experiment).
    scenario_id : str
        Environment scenario that replays it, e.g. ``"openacc-s-v1"``.
    file_name : str
        Trimmed file shipped in ``envs/data/openacc/``.
    source_file_name : str
        Original JRC file the trimmed copy was cut from.
    t_start_s, t_end_s : float
        Window bounds in the file's ``Time`` base [s], both included (601 samples).
    target_gap_m : float
        Target gap d* of the scenario [m].
    target_speed_mps : float
        Target speed v* of the scenario [m/s].
    distance_setting : str
        ACC distance setting of the experiment (header line 5).
    note : str
        Caveat to show wherever results of this window are reported ("" if none).
    """

    name: str
    scenario_id: str
    file_name: str
    source_file_name: str
    t_start_s: float
    t_end_s: float
    target_gap_m: float
    target_speed_mps: float
    distance_setting: str
    note: str = ""

    @property
    def n_samples(self) -> int:
        """Number of samples from ``t_start_s`` to ``t_end_s`` inclusive at ``DT_S`` (601)."""
        return round((self.t_end_s - self.t_start_s) / DT_S) + 1


_M_NOTE = (
    "Window M replays ZalaZONE dynamic_part8, 1250..1310 s, as a stand-in for the paper's "
    "dynamic_part9, 473..533 s (no public copy of part9 was found). Its leader runs at about "
    "8 m/s, not 11 m/s, and drops to 4.41 m/s; results on M are not directly comparable with "
    "the paper's."
)


def _zalazone_window(setting: str, part: int, t_start_s: int, target_gap_m: float,
                     note: str = "") -> OpenACCWindowSpec:
    """The 60 s window from ``t_start_s`` of ZalaZONE ``dynamic_part<part>`` at the ACC distance
    setting ``setting`` (its name), replayed by ``openacc-<setting>-v1`` at v* = 11 m/s."""
    t_end_s = t_start_s + 60
    return OpenACCWindowSpec(
        name=setting, scenario_id=f"openacc-{setting.lower()}-v1",
        file_name=f"ZalaZONE_dynamic_part{part}_{t_start_s}-{t_end_s}s.csv",
        source_file_name=f"ZalaZONE_dynamic_part{part}.csv", t_start_s=float(t_start_s),
        t_end_s=float(t_end_s), target_gap_m=target_gap_m, target_speed_mps=11.0,
        distance_setting=setting, note=note)


#: The three benchmark windows, by name.
WINDOWS: dict[str, OpenACCWindowSpec] = {w.name: w for w in (
    _zalazone_window("S", 1, 316, 12.0),
    _zalazone_window("M", 8, 1250, 16.0, _M_NOTE),
    _zalazone_window("L", 2, 450, 20.0),
)}


@dataclass(frozen=True)
class OpenACCHeader:
    """The 5 metadata lines of an OpenACC file.

    Attributes
    ----------
    date : str
        Experiment date as ``YYYY-MM-DD`` (line 1, ``Date,DD,MM,YYYY``).
    vehicle_names : tuple of str
        Vehicle order (line 2), leader first; trailing empty fields dropped.
    n_vehicles : int
        Number of vehicles (line 3), leader included.
    acc_mode : str
        ``ACC`` field (line 4): 0 all manual, 1 all followers on ACC, 2 mixed.
    distance_setting : str
        ``Distance_setting`` field (line 5): S, M, L (ZalaZONE) or min, max, none.
    """

    date: str
    vehicle_names: tuple[str, ...]
    n_vehicles: int
    acc_mode: str
    distance_setting: str


@dataclass(frozen=True, eq=False)
class OpenACCWindow:
    """One replay window of real platoon data (601 samples at 0.1 s).

    Arrays are read-only (they are shared by a cache); copy them before changing them.
    K is the number of followers asked for (``n_followers``), at most
    ``n_followers_available``.

    Attributes
    ----------
    name : str
        ``"S"``, ``"M"`` or ``"L"``.
    scenario_id : str
        Scenario that replays this window, e.g. ``"openacc-s-v1"``.
    file_name : str
        Shipped (trimmed) file read.
    source_file_name : str
        Original JRC file name.
    t_start_s, t_end_s : float
        Window bounds in the file's time base [s].
    n_followers_available : int
        Followers in the file (vehicles - 1): 5 for S and L, 4 for M.
    time_s : numpy.ndarray, shape (T,)
        File times of the samples [s], ``t_start_s`` .. ``t_end_s``.
    leader_speed_mps : numpy.ndarray, shape (T,)
        Leader speed ``Speed1`` [m/s].
    leader_accel_mps2 : numpy.ndarray, shape (T,)
        ``np.gradient`` of the leader speed [m/s^2], unsmoothed.
    follower_speed_mps : numpy.ndarray, shape (T, K)
        Follower k's speed ``Speed{k+1}`` [m/s] in column k - 1.
    follower_gap_m : numpy.ndarray, shape (T, K)
        Follower k's gap to its predecessor, ``IVS{k}`` [m].
    follower_accel_mps2 : numpy.ndarray, shape (T, K)
        ``np.gradient(speed, 0.1)`` of each follower [m/s^2], unsmoothed.
    vehicle_names : tuple of str
        All vehicles of the file (header line 2), leader first.
    distance_setting : str
        ACC distance setting of the experiment (header line 5).
    target_gap_m, target_speed_mps : float
        Scenario targets d* and v*.
    n_nan_filled : int
        NaN values filled by interpolation inside the window in the columns used
        (``Speed1..`` and ``IVS1..`` of the vehicles returned).
    note : str
        Caveat to show with results ("" if none); for M the part8-for-part9 substitution.
    """

    name: str
    scenario_id: str
    file_name: str
    source_file_name: str
    t_start_s: float
    t_end_s: float
    n_followers_available: int
    time_s: np.ndarray
    leader_speed_mps: np.ndarray
    leader_accel_mps2: np.ndarray
    follower_speed_mps: np.ndarray
    follower_gap_m: np.ndarray
    follower_accel_mps2: np.ndarray
    vehicle_names: tuple[str, ...]
    distance_setting: str
    target_gap_m: float
    target_speed_mps: float
    n_nan_filled: int
    note: str = ""

    @property
    def n_followers(self) -> int:
        """Number of followers K in the arrays."""
        return int(self.follower_speed_mps.shape[1])

    @property
    def n_samples(self) -> int:
        """Number of samples T (601)."""
        return int(self.time_s.shape[0])

    @property
    def dt_s(self) -> float:
        """Sample time [s] (0.1)."""
        return DT_S

    @property
    def follower_names(self) -> tuple[str, ...]:
        """Names of the K followers returned, front to back."""
        return self.vehicle_names[1 : 1 + self.n_followers]


@dataclass(frozen=True, eq=False)
class RealFollowersRecord:
    """The real ACC followers of a window as a baseline run ("OpenACC" row of the paper).

    Attributes
    ----------
    window : str
        Window name.
    time_s : numpy.ndarray, shape (T,)
        Sample times [s].
    leader_speed_mps : numpy.ndarray, shape (T,)
        Leader speed [m/s].
    speed_mps : numpy.ndarray, shape (T, K)
        Follower speeds [m/s].
    gap_m : numpy.ndarray, shape (T, K)
        Follower gaps to their predecessors [m].
    accel_mps2 : numpy.ndarray, shape (T, K)
        Follower accelerations from differentiated speed [m/s^2].
    power_kw : numpy.ndarray or None, shape (T, K)
        Battery power from ``envs.energy.battery_power_kw(..., model="poly")`` [kW], or None
        (``with_energy=False``).
    energy_kwh : numpy.ndarray or None, shape (K,)
        Energy per follower over the window [kWh], ``envs.energy.energy_kwh(power_kw, 0.1)``
        (rectangle rule over all T samples, regeneration counted negative), or None.
    """

    window: str
    time_s: np.ndarray
    leader_speed_mps: np.ndarray
    speed_mps: np.ndarray
    gap_m: np.ndarray
    accel_mps2: np.ndarray
    power_kw: np.ndarray | None = None
    energy_kwh: np.ndarray | None = None

    @property
    def n_followers(self) -> int:
        """Number of followers K."""
        return int(self.speed_mps.shape[1])

    def as_dict(self) -> dict[str, Any]:
        """Return the record as a plain dict (energy entries only when available)."""
        return {k: v for k, v in vars(self).items() if v is not None}


# -------------------------------------------------------------------------- reading and validation


def read_openacc_header(path: str | Path) -> OpenACCHeader:
    """Read the 5 metadata lines of an OpenACC CSV file.

    Parameters
    ----------
    path : str or pathlib.Path
        The CSV file.

    Returns
    -------
    OpenACCHeader
        The parsed metadata.

    Raises
    ------
    OpenACCDataError
        If the file is missing or unreadable, or a metadata line is not the expected one.
    """
    path = Path(path)
    where = f"OpenACC file {str(path)!r}"
    if not path.is_file():
        raise OpenACCDataError(f"{where} not found")
    try:
        with path.open(encoding="utf-8", newline=None) as fh:
            lines = [fh.readline().rstrip("\r\n") for _ in range(N_METADATA_LINES)]
    except (OSError, UnicodeDecodeError) as exc:
        raise OpenACCDataError(f"{where}: cannot read: {exc}") from exc
    fields: list[list[str]] = []
    for i, (key, line) in enumerate(zip(_HEADER_KEYS, lines), start=1):
        parts = [p.strip() for p in line.split(",")]
        if parts[0] != key:
            raise OpenACCDataError(f"{where}: metadata line {i} should start with {key!r}, "
                                   f"got {line[:60]!r}")
        while parts and parts[-1] == "":
            parts.pop()
        fields.append(parts[1:])
    date_parts = fields[0]
    if len(date_parts) == 3 and all(p.isdigit() for p in date_parts):
        day, month, year = (int(p) for p in date_parts)
        date = f"{year:04d}-{month:02d}-{day:02d}"
    else:
        date = ",".join(date_parts)
    try:
        n_vehicles = int(fields[2][0])
    except (IndexError, ValueError) as exc:
        raise OpenACCDataError(f"{where}: metadata line 3 has no integer Number_of_vehicles"
                               ) from exc
    if n_vehicles < 1:
        raise OpenACCDataError(f"{where}: Number_of_vehicles is {n_vehicles}, expected >= 1")
    return OpenACCHeader(
        date=date,
        vehicle_names=tuple(fields[1]),
        n_vehicles=n_vehicles,
        acc_mode=fields[3][0] if fields[3] else "",
        distance_setting=fields[4][0] if fields[4] else "",
    )


def _nan_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Return ``(start, stop)`` index pairs of the True runs of a 1-D boolean mask."""
    padded = np.concatenate(([False], mask, [False])).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def _fill_column(values: np.ndarray, time_s: np.ndarray) -> np.ndarray:
    """Fill NaNs: linear interpolation in time inside, nearest valid value at the ends."""
    nan = np.isnan(values)
    out = values.copy()
    # np.interp holds the end values outside the valid range: nearest-value fill at the ends.
    out[nan] = np.interp(time_s[nan], time_s[~nan], values[~nan])
    return out


def _line_no(row: int) -> int:
    """1-based line number in the file of data row ``row`` (0-based)."""
    return N_METADATA_LINES + 2 + row


def _read_validated(
    path: Path,
    columns: tuple[str, ...] | None,
    max_nan_run_rows: int,
) -> tuple[pd.DataFrame, np.ndarray, OpenACCHeader]:
    """Read, validate and fill; return the frame, the filled-cell mask (rows, cols), the header."""
    import pandas as pd

    header = read_openacc_header(path)
    where = f"OpenACC file {str(path)!r}"
    if columns is None:
        n = header.n_vehicles
        columns = ("Time", *(f"Speed{i}" for i in range(1, n + 1)),
                   *(f"IVS{i}" for i in range(1, n)))
    elif "Time" not in columns:
        columns = ("Time", *columns)
    try:
        present = pd.read_csv(path, skiprows=N_METADATA_LINES, nrows=0).columns
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise OpenACCDataError(f"{where}: cannot parse the column-name line: {exc}") from exc
    present_names = {str(c).strip() for c in present}
    missing = [c for c in columns if c not in present_names]
    if missing:
        raise OpenACCDataError(f"{where}: missing required columns {missing}")
    try:
        df = pd.read_csv(
            path,
            skiprows=N_METADATA_LINES,
            usecols=lambda c: str(c).strip() in columns,
            skipinitialspace=True,
        )
    except (pd.errors.ParserError, ValueError, UnicodeDecodeError) as exc:
        raise OpenACCDataError(f"{where}: cannot parse the data rows: {exc}") from exc
    df.columns = [str(c).strip() for c in df.columns]
    df = df.loc[:, list(columns)]
    if len(df) < 2:
        raise OpenACCDataError(f"{where}: fewer than 2 data rows")

    # Non-numeric values.
    for col in columns:
        series = df[col]
        if not pd.api.types.is_numeric_dtype(series):
            coerced = pd.to_numeric(series, errors="coerce")
            bad = np.flatnonzero((coerced.isna() & series.notna()).to_numpy())
            row = int(bad[0]) if bad.size else 0
            raise OpenACCDataError(
                f"{where}: non-numeric value {series.iloc[row]!r} in column {col!r} "
                f"at line {_line_no(row)} ({bad.size} such values)"
            )
        if pd.api.types.is_bool_dtype(series):
            raise OpenACCDataError(f"{where}: column {col!r} holds booleans, not numbers")
    data = df.to_numpy(dtype=np.float64)
    inf_rows, inf_cols = np.nonzero(np.isinf(data))
    if inf_rows.size:
        raise OpenACCDataError(
            f"{where}: infinite value in column {columns[int(inf_cols[0])]!r} "
            f"at line {_line_no(int(inf_rows[0]))}"
        )

    # Time base.
    time_s = data[:, 0]
    nan_t = np.flatnonzero(np.isnan(time_s))
    if nan_t.size:
        raise OpenACCDataError(f"{where}: empty Time at line {_line_no(int(nan_t[0]))}")
    step = np.diff(time_s)
    bad_order = np.flatnonzero(step <= 0)
    if bad_order.size:
        r = int(bad_order[0]) + 1
        raise OpenACCDataError(
            f"{where}: Time is not strictly increasing at line {_line_no(r)} "
            f"({time_s[r - 1]:g} s then {time_s[r]:g} s)"
        )
    bad_step = np.flatnonzero(np.abs(step - DT_S) > DT_TOL_S)
    if bad_step.size:
        r = int(bad_step[0]) + 1
        raise OpenACCDataError(
            f"{where}: time step of {step[r - 1]:.4g} s at line {_line_no(r)} "
            f"(t = {time_s[r]:g} s), expected {DT_S} s +- {DT_TOL_S} s "
            f"({bad_step.size} such steps)"
        )

    # NaN runs: fill the short ones, reject the long ones.
    filled = np.zeros(data.shape, dtype=bool)
    for j in range(1, data.shape[1]):
        nan = np.isnan(data[:, j])
        if not nan.any():
            continue
        if nan.all():
            raise OpenACCDataError(f"{where}: column {columns[j]!r} has no values")
        for a, b in _nan_runs(nan):
            if b - a > max_nan_run_rows:
                raise OpenACCDataError(
                    f"{where}: column {columns[j]!r} has a run of {b - a} missing values "
                    f"(lines {_line_no(a)}..{_line_no(b - 1)}, t = {time_s[a]:g}.."
                    f"{time_s[b - 1]:g} s), longer than the {max_nan_run_rows} rows "
                    f"that are interpolated"
                )
        data[:, j] = _fill_column(data[:, j], time_s)
        filled[:, j] = nan
    out = pd.DataFrame(data, columns=list(columns), index=df.index)
    return out, filled, header


def read_openacc_csv(
    path: str | Path,
    columns: tuple[str, ...] | list[str] | None = None,
    *,
    max_nan_run_rows: int = MAX_NAN_RUN_ROWS,
) -> pd.DataFrame:
    """Read and validate an OpenACC CSV file, filling short NaN runs.

    The file is read with ``pandas.read_csv(path, skiprows=5)`` and the columns are selected by
    name. NaN runs of at most ``max_nan_run_rows`` rows are filled by linear interpolation in
    time; a run that touches the first or last row is filled with the nearest valid value.

    Parameters
    ----------
    path : str or pathlib.Path
        The CSV file (OpenACC format, 5 metadata lines).
    columns : sequence of str, optional
        Columns to return (``Time`` is always included, first). Default: ``Time``,
        ``Speed1..SpeedN`` and ``IVS1..IVS(N-1)``, N from ``Number_of_vehicles``.
    max_nan_run_rows : int
        Longest run of consecutive NaN rows in a column that is filled (default 20 = 2 s).

    Returns
    -------
    pandas.DataFrame
        float64 columns in the order asked for. ``df.attrs`` holds ``"path"`` (str),
        ``"header"`` (:class:`OpenACCHeader`), ``"n_nan_filled"`` (dict column -> number of
        filled values) and ``"n_nan_filled_total"`` (int).

    Raises
    ------
    OpenACCDataError
        Naming the file and the problem: missing file, malformed metadata, missing columns,
        non-numeric or infinite values, empty or non-increasing ``Time``, a time step more than
        0.01 s away from 0.1 s, a column without values or a NaN run longer than the limit.
    """
    if max_nan_run_rows < 0:
        raise ConfigError(f"max_nan_run_rows must be >= 0, got {max_nan_run_rows}")
    cols = None if columns is None else tuple(columns)
    df, filled, header = _read_validated(Path(path), cols, max_nan_run_rows)
    counts = {str(c): int(n) for c, n in zip(df.columns, filled.sum(axis=0))}
    df.attrs["path"] = str(path)
    df.attrs["header"] = header
    df.attrs["n_nan_filled"] = counts
    df.attrs["n_nan_filled_total"] = int(sum(counts.values()))
    return df


# ----------------------------------------------------------------------------------------- windows


def _spec(name: str) -> OpenACCWindowSpec:
    """Return the window spec for a (case-insensitive) name, or raise listing valid names."""
    key = name.strip().upper() if isinstance(name, str) else name
    if key not in WINDOWS:
        raise UnknownNameError("OpenACC window", str(name), WINDOWS)
    return WINDOWS[key]


def data_path(name: str) -> Path:
    """Return the path of the shipped trimmed file of window ``name`` ("S", "M" or "L").

    Parameters
    ----------
    name : str
        Window name (case-insensitive).

    Returns
    -------
    pathlib.Path
        Path inside the installed package (``envs/data/openacc/``).
    """
    resource = importlib.resources.files("envs").joinpath("data", "openacc", _spec(name).file_name)
    return Path(str(resource))


@dataclass(frozen=True, eq=False)
class _WindowArrays:
    """Full-file arrays of a window, cached (all followers, read-only)."""

    time_s: np.ndarray
    speed_mps: np.ndarray  # (T, n_vehicles)
    accel_mps2: np.ndarray  # (T, n_vehicles)
    gap_m: np.ndarray  # (T, n_vehicles - 1)
    filled: np.ndarray  # (T, n_vehicles + n_vehicles - 1): Speed1.. then IVS1..
    header: OpenACCHeader


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


@functools.lru_cache(maxsize=8)
def _window_arrays(name: str) -> _WindowArrays:
    spec = WINDOWS[name]
    path = data_path(name)
    df, filled, header = _read_validated(path, None, MAX_NAN_RUN_ROWS)
    n = header.n_vehicles
    time_s = df["Time"].to_numpy()
    speed = df[[f"Speed{i}" for i in range(1, n + 1)]].to_numpy()
    gap = df[[f"IVS{i}" for i in range(1, n)]].to_numpy()
    accel = np.gradient(speed, DT_S, axis=0)
    # Pick the samples t_start, t_start + 0.1, ..., t_end by time, not by row index.
    grid = spec.t_start_s + DT_S * np.arange(spec.n_samples)
    idx = np.clip(np.searchsorted(time_s, grid - TIME_MATCH_TOL_S), 0, len(time_s) - 1)
    off = np.abs(time_s[idx] - grid) > TIME_MATCH_TOL_S
    if off.any():
        t_missing = float(grid[np.flatnonzero(off)[0]])
        raise OpenACCDataError(
            f"OpenACC file {str(path)!r}: no sample within {TIME_MATCH_TOL_S} s of "
            f"t = {t_missing:g} s (window {spec.t_start_s:g}..{spec.t_end_s:g} s)"
        )
    return _WindowArrays(
        time_s=_readonly(time_s[idx]),
        speed_mps=_readonly(speed[idx]),
        accel_mps2=_readonly(accel[idx]),
        gap_m=_readonly(gap[idx]),
        filled=_readonly(filled[idx, 1:]),
        header=header,
    )


def load_window(name: str, n_followers: int | None = None) -> OpenACCWindow:
    """Load one benchmark replay window from the shipped files.

    Parameters
    ----------
    name : str
        ``"S"``, ``"M"`` or ``"L"`` (case-insensitive); see :data:`WINDOWS`.
    n_followers : int, optional
        Number of real followers to return, front to back (default: all in the file,
        5 for S and L, 4 for M; the paper uses 4).

    Returns
    -------
    OpenACCWindow
        601 samples at 0.1 s from ``t_start_s`` to ``t_end_s`` inclusive, selected by time.

    Raises
    ------
    UnknownNameError
        For an unknown window name (a ``KeyError``; the message lists the valid names).
    ConfigError
        If ``n_followers`` is below 1 or more than the file has (a ``ValueError``).
    OpenACCDataError
        If the shipped file is missing or malformed.
    """
    spec = _spec(name)
    arrays = _window_arrays(spec.name)
    available = arrays.header.n_vehicles - 1
    n_followers = available if n_followers is None else n_followers
    if isinstance(n_followers, bool) or not isinstance(n_followers, int | np.integer):
        raise ConfigError(f"n_followers must be an integer, got {n_followers!r}")
    n_followers = int(n_followers)
    if not 1 <= n_followers <= available:
        raise ConfigError(
            f"OpenACC window {spec.name} ({spec.file_name}) has {available} followers; "
            f"asked for {n_followers}"
        )
    k, n = n_followers, arrays.header.n_vehicles
    used = np.r_[0 : k + 1, n : n + k]  # Speed1..Speed(k+1), IVS1..IVSk in the filled mask
    return OpenACCWindow(
        name=spec.name,
        scenario_id=spec.scenario_id,
        file_name=spec.file_name,
        source_file_name=spec.source_file_name,
        t_start_s=spec.t_start_s,
        t_end_s=spec.t_end_s,
        n_followers_available=available,
        time_s=arrays.time_s,
        leader_speed_mps=arrays.speed_mps[:, 0],
        leader_accel_mps2=arrays.accel_mps2[:, 0],
        follower_speed_mps=arrays.speed_mps[:, 1 : k + 1],
        follower_gap_m=arrays.gap_m[:, :k],
        follower_accel_mps2=arrays.accel_mps2[:, 1 : k + 1],
        vehicle_names=arrays.header.vehicle_names,
        distance_setting=arrays.header.distance_setting,
        target_gap_m=spec.target_gap_m,
        target_speed_mps=spec.target_speed_mps,
        n_nan_filled=int(arrays.filled[:, used].sum()),
        note=spec.note,
    )


def real_followers_record(
    window: OpenACCWindow | str,
    n_followers: int | None = None,
    *,
    with_energy: bool = True,
) -> RealFollowersRecord:
    """Return the real ACC followers of a window as a baseline record.

    Parameters
    ----------
    window : OpenACCWindow or str
        A loaded window, or a window name to load.
    n_followers : int, optional
        Number of followers, front to back (default: all in ``window``).
    with_energy : bool
        If True, add ``power_kw`` (the ``"poly"`` battery power model at each sample) and
        ``energy_kwh`` per follower (``envs.energy.energy_kwh(power_kw, 0.1)``: rectangle rule
        over the T samples, regeneration negative).

    Returns
    -------
    RealFollowersRecord
        Arrays of shape (T, K): ``speed_mps``, ``gap_m``, ``accel_mps2``.

    Raises
    ------
    ConfigError
        If ``n_followers`` is below 1 or more than the window holds.
    """
    win = load_window(window, n_followers) if isinstance(window, str) else window
    k = win.n_followers if n_followers is None else int(n_followers)
    if not 1 <= k <= win.n_followers:
        raise ConfigError(
            f"OpenACC window {win.name} holds {win.n_followers} followers; asked for {k}"
        )
    speed = win.follower_speed_mps[:, :k]
    accel = win.follower_accel_mps2[:, :k]
    power_kw = energy = None
    if with_energy:
        from envs.energy import battery_power_kw, energy_kwh

        power_kw = np.asarray(battery_power_kw(speed, accel, model="poly"), dtype=np.float64)
        energy = np.asarray(energy_kwh(power_kw, DT_S, axis=0), dtype=np.float64)
    return RealFollowersRecord(
        window=win.name,
        time_s=win.time_s,
        leader_speed_mps=win.leader_speed_mps,
        speed_mps=speed,
        gap_m=win.follower_gap_m[:, :k],
        accel_mps2=accel,
        power_kw=power_kw,
        energy_kwh=energy,
    )
