"""Names with options, one grammar for controllers and scenarios.

On the command line: ``name:key=value,key=value`` in a comma list, where a ``key=value`` item
belongs to the name before it (``mpc:horizon=30,solver=ipopt,cacc``). In labels (the leaderboard,
the store): ``name[key=value,...]`` with the keys sorted. Both forms parse back.

A name may also be a reference to an object in the user's own code, ``package.module:Attribute``
(the grammar of Python entry points), with its options after a further colon:
``my_pkg.laws:MyController:gain=2``. An item is a reference when it starts with dotted Python
identifiers, a colon and a dotted identifier, followed by nothing, ``:`` or ``[`` (a registered
name with an option, ``mpc:horizon=30``, never is: ``=`` follows).
"""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

from infra.errors import ConfigError

T = TypeVar("T")

#: ``package.module:Attribute``: a reference to an object in Python code (entry-point grammar).
REFERENCE = re.compile(r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*")


def split_reference(item: str) -> tuple[str, str] | None:
    """``("pkg.mod:Attr", "key=value,...")`` for an item that is a reference, with what follows
    its further colon (``""`` if nothing); None for any other item (``mpc:horizon=30``,
    ``sine-v1``, a label with brackets)."""
    m = REFERENCE.match(item)
    if m is None:
        return None
    rest = item[m.end():]
    if not rest:
        return m.group(), ""
    if rest.startswith(":"):
        return m.group(), rest[1:]
    return None


def is_reference(name: str) -> bool:
    """Whether ``name`` is exactly a ``package.module:Attribute`` reference."""
    return REFERENCE.fullmatch(name) is not None


def parse_named_list(text: str, kind: str, name_prefixes: tuple[str, ...] = ()
                     ) -> list[tuple[str, dict[str, str]]]:
    """Parse ``"mpc:solver=ipopt,horizon=30,cacc"`` into ``[("mpc", {...}), ("cacc", {})]``;
    labels (``"sine-v1[amplitude_mps=2]"``) are accepted as items too. An item that starts with
    one of ``name_prefixes`` (``"safe:"``, repeated or not) keeps it in its name:
    ``safe:bdc:seed=1`` is ``("safe:bdc", {"seed": "1"})``; a reference keeps its colon:
    ``my_mod:MyLaw:gain=2`` is ``("my_mod:MyLaw", {"gain": "2"})``."""
    out: list[tuple[str, dict[str, str]]] = []
    for raw in _split_outside_brackets(text):
        item = raw.strip()
        if not item:
            continue
        prefix = ""
        while name_prefixes and item.startswith(name_prefixes):
            p = next(p for p in name_prefixes if item.startswith(p))
            prefix, item = prefix + p, item[len(p):]
        if "[" in item:
            name, options = parse_label(item, kind)
            out.append((prefix + name, options))
            continue
        head = split_reference(item)
        if head is None and (prefix or ":" in item):
            name, _, opt = item.partition(":")
            head = name.strip(), opt
        if head is not None:  # a name, then its first option (if any)
            out.append((prefix + head[0], {}))
            item = head[1]
            if not item:
                continue
        elif "=" not in item:
            out.append((item, {}))
            continue
        if "=" not in item:
            raise ConfigError(f"{kind} option {item!r} must be written key=value")
        if not out:
            raise ConfigError(f"option {item!r} comes before any {kind} name")
        key, value = item.split("=", 1)
        _set_once(out[-1][1], key.strip(), value.strip(), f"{kind} {out[-1][0]}")
    if not out:
        raise ConfigError(f"no {kind} named")
    return out


def _set_once(options: dict[str, str], key: str, value: str, owner: str) -> None:
    """``options[key] = value``, refusing a key given twice (ConfigError): the last would win
    without a word."""
    if key in options:
        raise ConfigError(f"{owner}: option {key} given twice ({options[key]!r} and {value!r}); "
                          "give it once")
    options[key] = value


def _split_outside_brackets(text: str) -> list[str]:
    parts: list[str] = []
    cur: list[str] = []
    depth = 0
    for ch in text:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth = max(depth - 1, 0)
        if ch == "," and depth == 0:
            parts.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    parts.append("".join(cur))
    return parts


def format_label(name: str, options: dict[str, Any]) -> str:
    """``name`` or ``name[key=value,...]`` (keys sorted)."""
    if not options:
        return name
    return name + "[" + ",".join(f"{k}={options[k]}" for k in sorted(options)) + "]"


def canonical_value(value: Any) -> Any:
    """The one spelling of a typed option value in a label, so one setting is one label:
    ``true``/``false``; an integer in decimal; a float as the shortest decimal that reads back
    as it, without a trailing ``.0`` (``2``, ``2.0``, ``2e0`` and ``+2`` are all ``2``; ``0.1``;
    ``1e-05``); a path with its links resolved, relative to the working directory when inside
    it (``checkpoints``), else absolute. Other values come back unchanged."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        text = repr(value + 0.0)  # -0.0 is 0
        return text.removesuffix(".0")
    if isinstance(value, Path):
        resolved = value.expanduser().resolve()
        here = Path.cwd().resolve()
        return (resolved.relative_to(here) if resolved.is_relative_to(here)
                else resolved).as_posix()
    return value


def merge_repeats(items: Sequence[T], labels: Sequence[str], option: str
                  ) -> tuple[list[T], str]:
    """``items`` once per canonical label, in order (the first of each kept), and the one line
    a command prints on standard error when some were named more than once ('' if none): one
    setting named twice (``cacc,cacc:kp=2.0,cacc:kp=2``) runs, and is reported, once."""
    first: dict[str, T] = {}
    for label, item in zip(labels, items, strict=True):
        first.setdefault(label, item)
    twice = [label for label in first if labels.count(label) > 1]
    note = f"{option}: {', '.join(twice)} named more than once; each is used once" if twice else ""
    return list(first.values()), note


def parse_label(label: str, kind: str = "name") -> tuple[str, dict[str, str]]:
    """``"name[k=v,...]"`` or ``"name:k=v,..."`` or ``"name"`` -> ``(name, {k: v})``."""
    text = label.strip()
    if text.endswith("]") and "[" in text:
        name, inner = text[:-1].split("[", 1)
    elif (reference := split_reference(text)) is not None:
        name, inner = reference
    elif ":" in text:
        name, inner = text.split(":", 1)
    else:
        return text, {}
    options: dict[str, str] = {}
    for item in inner.split(","):
        if not item.strip():
            continue
        if "=" not in item:
            raise ConfigError(f"{kind} option {item.strip()!r} in {label!r} must be key=value")
        key, value = item.split("=", 1)
        _set_once(options, key.strip(), value.strip(), f"{kind} {name.strip()}")
    return name.strip(), options


def checkpoint_stem(algo: str, scenario_id: str, n_vehicles: int, seed: int) -> str:
    """File stem of a trained policy: ``<algo>__<scenario>__n<N>__s<seed>`` (the one rule the
    trainers write by and the policy controllers load by)."""
    return f"{algo}__{scenario_id}__n{n_vehicles}__s{seed}"


def coerce_option(value: Any, annotation: Any, key: str, owner: str) -> Any:
    """A command-line option value (a string) as the type ``annotation`` names (``bool``,
    ``int``, ``float``, ``Path``, ``X | None``); other values and types pass unchanged. The one
    rule for controller, scenario and learner options.

    Raises
    ------
    ConfigError
        If the string is not of that type (floats must be finite, a path not empty).
    """
    if not isinstance(value, str):
        return value
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is not None and type(None) in args:
        annotation = next(a for a in args if a is not type(None))
        if value.lower() == "none" or (value == "" and annotation is str):
            return None
    if not value.strip() and annotation in (bool, int, float, "bool", "int", "float"):
        raise ConfigError(f"option {key} of {owner} has no value; give one, or leave the "
                          "option out for its default")
    if annotation is Path:
        if not value.strip():
            raise ConfigError(f"option {key} of {owner} names no path; give one, or leave the "
                              "option out")
        return Path(value)
    try:
        if annotation in (bool, "bool"):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError
        if annotation in (int, "int"):
            return int(value)
        if annotation in (float, "float"):
            out = float(value)
            if not math.isfinite(out):
                raise ValueError
            return out
    except ValueError:
        raise ConfigError(
            f"option {key} of {owner} must be of type "
            f"{getattr(annotation, '__name__', annotation)}, got {value!r}"
        ) from None
    return value


def build_config(config_cls: type, options: dict[str, Any], owner: str) -> Any:
    """Instantiate a frozen config dataclass from keyword options, coercing strings by type.

    Unknown options give a :class:`ConfigError` listing the valid ones; the dataclass's own
    ``__post_init__`` checks values.
    """
    fields = {f.name: f for f in dataclasses.fields(config_cls) if f.init}
    hints = typing.get_type_hints(config_cls)
    kwargs = {}
    for key, value in options.items():
        if key not in fields:
            raise ConfigError(
                f"{owner} has no option {key!r}; its options are: {', '.join(sorted(fields))}"
            )
        kwargs[key] = coerce_option(value, hints.get(key, str), key, owner)
    try:
        return config_cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"bad options for {owner}: {exc}") from None
