"""Objects from the user's own code: ``package.module:Attribute`` references and entry points.

A controller or a scenario need not live in this package: ``--controllers my_laws:MyLaw`` names
a class in the user's module ``my_laws`` (:func:`infra.naming.split_reference` is the grammar),
and an installed package adds names through an entry-point group (``cacc_bench.controllers``,
``cacc_bench.scenarios``). This module imports what a reference names, the one way for both
registries, and turns every way it can fail into one :class:`infra.errors.ConfigError` line.

A module is looked up on the Python path (``sys.path``: the installed packages, ``PYTHONPATH``),
then in the working directory, as ``python -m`` would find it; the directory is then added to
the end of ``sys.path``, which process workers inherit (and Ray adds the driver's working
directory to its workers' path).
"""

from __future__ import annotations

import functools
import importlib
import importlib.machinery
import importlib.metadata
import importlib.util
import os
import sys
from collections.abc import Callable
from types import ModuleType
from typing import Any, TypeVar

from infra.errors import ConfigError
from infra.naming import is_reference

T = TypeVar("T")


def first_line(exc: BaseException) -> str:
    """``Type: first line of the message`` of an error raised by the user's code, or ``it called
    sys.exit(code)`` for a :class:`SystemExit`."""
    if isinstance(exc, SystemExit):
        return f"it called sys.exit({exc.code!r})"
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _findable(top: str) -> bool:
    try:
        return importlib.util.find_spec(top) is not None
    except (ImportError, ValueError):
        return False


def _import_module(module_name: str, who: str) -> ModuleType:
    top = module_name.split(".", 1)[0]
    if not _findable(top):
        here = os.getcwd()
        if here in sys.path or importlib.machinery.PathFinder.find_spec(top, [here]) is None:
            raise ConfigError(
                f"{who}: no module {top!r} on the Python path or in the working directory; "
                f"put the folder that holds {top}.py (or the package {top}/) on PYTHONPATH, "
                "or install its package")
        sys.path.append(here)
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and (module_name == exc.name
                                     or module_name.startswith(exc.name + ".")):
            raise ConfigError(f"{who}: no module {module_name!r} (the package {top} has no "
                              f"{module_name.removeprefix(top + '.')})") from None
        raise ConfigError(f"{who}: importing {module_name} failed ({first_line(exc)}); install "
                          "what it imports") from None
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - the user's module: one line (its
        # sys.exit() would end the command, and `list`, silently)
        raise ConfigError(f"{who}: importing {module_name} failed ({first_line(exc)})") from None
    except KeyboardInterrupt as exc:
        if _raised_by_code(exc):  # else a real Ctrl-C or SIGTERM: the command's interrupt line
            raise ConfigError(f"{who}: importing {module_name} failed (it raised "
                              "KeyboardInterrupt itself; no signal was received)") from None
        raise


def _raised_by_code(exc: KeyboardInterrupt) -> bool:
    """Whether ``exc`` was raised by code rather than by a signal: the command line's handlers
    (:mod:`infra.interrupt`) raise :class:`infra.interrupt.Interrupted` and record the signal,
    so a plain KeyboardInterrupt while they are installed is the code's own; under Python's
    default handler the two cannot be told apart (a signal, then)."""
    import signal

    from infra.interrupt import Interrupted, received

    return (not isinstance(exc, Interrupted) and received() is None
            and signal.getsignal(signal.SIGINT) is not signal.default_int_handler)


def import_reference(reference: str, who: str) -> Any:
    """The object ``package.module:Attribute`` names (``Attribute`` may be dotted).

    Parameters
    ----------
    reference : str
        ``package.module:Attribute``.
    who : str
        What is being loaded, for messages (``controller my_laws:MyLaw``).

    Raises
    ------
    ConfigError
        If the text is not a reference, the module is not found or fails to import (its error's
        first line is kept), or it has no such attribute.
    """
    if not is_reference(reference):
        raise ConfigError(f"{who}: {reference!r} is not a reference; write package.module:Name, "
                          "e.g. my_controllers:MyController")
    module_name, _, attr = reference.partition(":")
    obj: Any = _import_module(module_name, who)
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise ConfigError(f"{who}: module {module_name} has no {attr!r} "
                              f"({getattr(obj, '__file__', module_name)})") from None
    return obj


def canonical_reference(obj: Any, given: str) -> str:
    """The one spelling of a reference to ``obj``: ``module:qualname`` where it is defined, when
    that names the same object (``pkg:Law`` re-exported from ``pkg.laws`` is ``pkg.laws:Law``),
    else ``given``; so one class is one leaderboard row however it was named."""
    module_name = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if not (isinstance(module_name, str) and isinstance(qualname, str)):
        return given
    here = f"{module_name}:{qualname}"
    if not is_reference(here) or module_name not in sys.modules:
        return given
    found: Any = sys.modules[module_name]
    for part in qualname.split("."):
        found = getattr(found, part, None)
    return here if found is obj else given


def load_plugin(cache: dict[str, T], kind: str, name: str, target: str,
                build: Callable[[Any, str], T]) -> T:
    """The plug-in ``name`` of a registry, built once: ``build(obj, who)`` of the object at
    ``target`` (:func:`import_reference`; ``name`` is the reference itself or an entry point's
    name), kept in ``cache`` by ``name``. ``who`` names it in messages: ``<kind> <name>``, with
    ``(<target>)`` for an entry point.

    Raises
    ------
    ConfigError
        As :func:`import_reference`, or as ``build`` refuses the object.
    """
    found = cache.get(name)
    if found is None:
        who = f"{kind} {name}" + (f" ({target})" if target != name else "")
        found = cache[name] = build(import_reference(target, who), who)
    return found


@functools.cache
def entry_points(group: str) -> dict[str, str]:
    """``name -> "package.module:Attribute"`` of the installed packages' entry points in
    ``group``, read from their metadata without importing them (first of a name wins; a value
    with extras, ``mod:Attr [extra]``, without them)."""
    out: dict[str, str] = {}
    for ep in importlib.metadata.entry_points(group=group):
        out.setdefault(ep.name, ep.value.split("[", 1)[0].strip())
    return out
