"""The ``full`` mark: checks CI runs beside the default test run.

The default run (the README's test command) stays short; CI adds ``-m full``: the numbers the
README and the committed reports quote, recomputed from the shipped files, and whole trainings
compared across executors, populations and devices. A check over every algorithm keeps one or
two of them in the default run (:func:`representative`), so each mechanism is tried there too.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable
from typing import Any

import pytest

FULL = pytest.mark.full


def representative(values: Iterable[Any], keep: Collection[Any]) -> list[Any]:
    """``values`` for ``pytest.mark.parametrize``: those in ``keep`` run by default, the others
    carry the ``full`` mark (a tuple value is one case of several arguments)."""
    out: list[Any] = []
    for v in values:
        if v in keep:
            out.append(v)
        else:
            out.append(pytest.param(*v, marks=FULL) if isinstance(v, tuple)
                       else pytest.param(v, marks=FULL))
    return out
