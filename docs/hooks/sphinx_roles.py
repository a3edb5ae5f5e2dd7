"""MkDocs hook (``hooks:`` in ``mkdocs.yml``): Sphinx cross-reference roles in docstrings.

The docstrings cite other objects the Sphinx way (``:func:`make_scenario```), which mkdocstrings
renders as the literal role followed by code; this drops the role and keeps the code, so the API
reference reads ``make_scenario`` rather than ``:func:make_scenario``.
"""

from __future__ import annotations

import re
from typing import Any

_ROLE = re.compile(r":(?:py:)?(?:attr|class|const|data|exc|func|meth|mod|obj):(?=<code>)")


def on_page_content(html: str, **kwargs: Any) -> str:
    """Drop the role before every ``<code>`` span it introduces."""
    return _ROLE.sub("", html)
