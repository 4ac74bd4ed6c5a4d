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


def save_figure(fig, path, *, dpi: int = 120, tight: bool = True):
    """Write the matplotlib figure ``fig`` to ``path`` (its format from the suffix) at
    ``dpi``, after ``fig.tight_layout()`` when ``tight``, and close it (a long sweep does
    not accumulate open figures). Returns ``path`` as a :class:`pathlib.Path`."""
    from pathlib import Path

    import matplotlib.pyplot as plt
    path = Path(path)
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
