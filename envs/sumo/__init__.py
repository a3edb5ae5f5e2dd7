"""The SUMO backend: the platoon env over Eclipse SUMO through libsumo (the ``sumo`` extra).

Nothing here imports libsumo at import time: :func:`sumo_available` looks for it without
importing it, so ``cacc-bench --help`` stays fast and an install without the extra refuses the
option with the install command (:func:`require_sumo`). The env is
:class:`envs.sumo.env.SumoPlatoonEnv`; its settings and their reasons: ``docs/sumo/index.md``.
"""

from __future__ import annotations

import importlib.util

from infra.errors import ConfigError

#: The SUMO releases the backend is written and tested against (``pyproject.toml``'s extra).
SUMO_VERSIONS = ">=1.28,<1.29"
#: The command that installs the extra.
INSTALL_COMMAND = "pip install -e '.[sumo]'"


def sumo_available() -> bool:
    """Whether ``libsumo`` and the ``sumo`` binaries package are installed (not imported)."""
    return all(importlib.util.find_spec(m) is not None for m in ("libsumo", "sumo"))


def require_sumo() -> None:
    """Raise a :class:`ConfigError` with the install command when SUMO is not installed, or
    when libsumo is installed but does not load (a wheel built for another system: its
    ``ImportError`` failed every run of a sweep, one by one). Imports libsumo: called where
    SUMO is about to run, never at import time."""
    if not sumo_available():
        raise ConfigError(
            "the SUMO simulator needs the sumo extra (eclipse-sumo and libsumo "
            f"{SUMO_VERSIONS}); install it with: {INSTALL_COMMAND}")
    try:
        import libsumo  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any failure to load is the same advice
        from infra.interrupt import raise_if_interrupted
        from infra.plugins import first_line

        raise_if_interrupted()  # a signal during the load ends it with an ImportError too
        raise ConfigError(
            f"libsumo is installed but does not load ({first_line(exc)}); reinstall the sumo "
            f"extra (eclipse-sumo and libsumo {SUMO_VERSIONS}): {INSTALL_COMMAND}") from None
