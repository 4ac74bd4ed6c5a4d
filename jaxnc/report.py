"""Plain-text / Markdown tables in the papers' style (inf shown as the symbol)."""
from __future__ import annotations

import math

INF = "\u221e"


def fmt(value, digits: int = 2) -> str:
    """Format a number; inf/nan (unstable) as the infinity symbol, None as the paper's dash."""
    if value is None:
        return "\u2013"
    if isinstance(value, str):
        return value
    if not math.isfinite(value):
        return INF
    return f"{value:.{digits}f}"


def markdown_table(header: list[str], rows: list[list]) -> str:
    """A Markdown table; the cells are strings already formatted."""
    cells = [[str(c) for c in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]
    line = lambda r: "| " + " | ".join(c.rjust(w) for c, w in zip(r, widths)) + " |"
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(header), sep, *(line(r) for r in cells)])
