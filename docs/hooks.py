"""mkdocs hook: render the Sphinx cross-reference roles of the package's docstrings
(``:class:`~afvsgp_gym.types.BarrierSet```) as plain code, as mkdocstrings leaves them."""

from __future__ import annotations

import re

_ROLE = re.compile(r":(?:py:)?(?:mod|class|func|meth|data|attr|exc|obj):<code>(~?)([^<]+)</code>")


def _code(match: re.Match) -> str:
    name = match.group(2)
    return f"<code>{name.rsplit('.', 1)[-1] if match.group(1) else name}</code>"


def on_page_content(html: str, **kwargs) -> str:
    return _ROLE.sub(_code, html)
