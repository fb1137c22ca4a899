"""Small helpers every part of the library shares: thread pinning and plain-text tables."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import torch

__all__ = ["num_threads", "format_table", "TABLE_WIDTH"]


@contextlib.contextmanager
def num_threads(n: int | None) -> Iterator[None]:
    """Run torch with ``n`` CPU threads inside the block, then restore the old count.

    ``None`` leaves the count as it is. Small models are bound by per-operation overhead, which
    more threads only increase: rollouts, data loading and the tests of tiny models run on one.
    """
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ValueError(f"n must be an integer >= 1 or None, got {n!r}")
    old = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _cell(v: Any, digits: int) -> str:
    if v is None:
        return "-"
    if isinstance(v, tuple) and len(v) == 2:  # (mean, interval half-width or std)
        return f"{_cell(v[0], digits)} ± {_cell(v[1], digits)}"
    if isinstance(v, float):
        return f"{v:.{digits}f}" if abs(v) < 100 else f"{v:.1f}"
    return str(v)


TABLE_WIDTH = 77
"""Characters of an output line that the book shows unscrolled: its 688-pixel column, less 32 px of
padding, holds 77 characters of 14-pixel monospace (8.4 px each)."""


def format_table(
    rows: Mapping[str, Mapping[str, Any]] | Sequence[Mapping[str, Any]],
    columns: Sequence[str] | None = None,
    digits: int = 2,
    first: str = "model",
    width: int | None = TABLE_WIDTH,
) -> str:
    """A fixed-width plain-text table.

    A table wider than ``width`` characters is printed as column groups, one under the other,
    each repeating the row names, so that no line is wider than ``width`` (unless one column
    alone is).

    Args:
        rows: ``{row name: {column: value}}``, or a list of dicts whose ``first`` key names
            the row. A value is a number, a string, ``None`` (printed ``-``) or a pair
            ``(mean, half-width)`` printed ``mean ± half-width``.
        columns: the columns, in order (default: every key, in order of appearance).
        digits: decimals of floats below 100 (larger ones get one).
        first: the header of the first column (and, for a list, the key that names a row).
        width: the widest line; None: one block however wide.
    """
    if isinstance(rows, Mapping):
        named = [(str(k), dict(v)) for k, v in rows.items()]
    else:
        named = [(str(r.get(first, "")), {k: v for k, v in r.items() if k != first}) for r in rows]
    if not named:
        raise ValueError("rows must hold at least one row")
    if width is not None and width < 1:
        raise ValueError(f"width must be >= 1 or None, got {width}")
    if columns is None:
        columns = list(dict.fromkeys(k for _, r in named for k in r))
    cells = {c: [c] + [_cell(r.get(c), digits) for _, r in named] for c in columns}
    names = [first] + [name for name, _ in named]
    name_w = max(map(len, names))
    groups: list[list[str]] = [[]]
    used = name_w
    for c in columns:
        w = 2 + max(map(len, cells[c]))
        if groups[-1] and width is not None and used + w > width:
            groups.append([])
            used = name_w
        groups[-1].append(c)
        used += w
    blocks = []
    for group in groups:
        cols = [[x.ljust(name_w) for x in names]]
        cols += [[x.rjust(max(map(len, cells[c]))) for x in cells[c]] for c in group]
        blocks.append("\n".join("  ".join(row) for row in zip(*cols, strict=True)))
    return "\n\n".join(blocks)
