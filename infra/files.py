"""Reading the files a command takes as input (JSON records, CSV tables): a file that cannot be
read, is not UTF-8, is not JSON or CSV, or lacks what it must hold is a ConfigError of one line
naming it and what to do, raised before any work that needs it, never a decoder's traceback."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from infra.errors import ConfigError

#: What to do about a damaged file, unless the reader says better.
RESTORE = "remove it or restore it, and rerun"


def damaged(path: str | Path, what: str, reason: str, fix: str = RESTORE) -> ConfigError:
    """The one message of a damaged input file: ``<what> <path> is damaged (<reason>); <fix>``."""
    reason = " ".join(str(reason).split())[:160]
    return ConfigError(f"{what} {path} is damaged ({reason}); {fix}")


def read_json(path: str | Path, what: str, fix: str = RESTORE) -> dict[str, Any]:
    """The JSON object in ``path`` (``what`` names the file in the message, e.g. ``the
    reproduction manifest``; ``fix`` says what to do about a damaged one).

    Raises
    ------
    ConfigError
        ``path`` cannot be read, is not UTF-8 JSON, or holds no JSON object.
    """
    try:
        value = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise damaged(path, what, f"cannot be read: {exc.strerror or exc}", fix) from None
    except ValueError as exc:  # JSONDecodeError and UnicodeDecodeError alike
        raise damaged(path, what, f"not JSON: {exc}", fix) from None
    if not isinstance(value, dict):
        raise damaged(path, what, f"a JSON {type(value).__name__}, not an object", fix)
    return value


def read_csv(path: str | Path, what: str, columns: Sequence[str] = (),
             numeric: Sequence[str] | bool = (), fix: str = RESTORE, **kwargs: Any) -> Any:
    """The table in the CSV file ``path`` (a pandas DataFrame; ``kwargs`` go to
    ``pandas.read_csv``), holding every one of ``columns``, and in each of ``numeric`` it holds
    (``True``: in every column) only numbers or empty cells.

    Raises
    ------
    ConfigError
        ``path`` cannot be read or parsed as UTF-8 CSV, lacks a column, or holds text where a
        number belongs.
    """
    import pandas as pd

    try:
        df = pd.read_csv(path, **kwargs)
    except OSError as exc:
        raise damaged(path, what, f"cannot be read: {exc.strerror or exc}", fix) from None
    except ValueError as exc:  # a parser error, no columns, not UTF-8
        raise damaged(path, what, f"not CSV: {exc}", fix) from None
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise damaged(path, what, f"no column {', '.join(missing)}", fix)
    for col in df.columns if numeric is True else [c for c in numeric or () if c in df.columns]:
        bad = df[col][pd.to_numeric(df[col], errors="coerce").isna() & df[col].notna()]
        if len(bad):
            raise damaged(path, what, f"column {col} holds {str(bad.iloc[0])[:20]!r}, not a "
                          "number", fix)
    return df
