"""The one text-table formatter of the CLI and the reports (``tabulate`` with our number style).

Numbers are shown with 4 significant digits, NaN as ``-``; columns whose key ends in ``_s``
(seconds) can be shown in microseconds with ``micro=True``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["format_table", "format_value"]


def format_value(v: Any) -> str:
    """A cell: integers as is, floats with 4 significant digits, NaN/None as ``-``."""
    if v is None:
        return "-"
    if isinstance(v, bool | np.bool_):
        return str(bool(v))
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        v = float(v)
        if math.isnan(v):
            return "-"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return f"{v:.4g}"
    return str(v)


def format_table(
    rows: Sequence[Mapping[str, Any]],
    columns: Sequence[str],
    headers: Sequence[str] | None = None,
    *,
    micro: bool = False,
    markdown: bool = False,
) -> str:
    """Rows (dicts) as a right-aligned text table (or a GitHub markdown table).

    ``columns`` are the keys shown, ``headers`` their titles (default: the keys); with
    ``micro`` a float in a column whose key ends in ``_s`` is shown in microseconds.
    """
    from tabulate import tabulate

    headers = list(columns if headers is None else headers)
    if len(headers) != len(columns):
        raise ValueError(f"{len(headers)} headers for {len(columns)} columns")
    cells = []
    for row in rows:
        line = []
        for c in columns:
            v = row.get(c)
            if micro and c.endswith("_s") and isinstance(v, float | np.floating):
                v = float(v) * 1e6
            line.append(format_value(v))
        cells.append(line)
    return tabulate(cells, headers, tablefmt="github" if markdown else "simple",
                    disable_numparse=True, stralign="right")
