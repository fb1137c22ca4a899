"""Results over seeds: read a benchmark's JSON lines and summarise them as mean ± std.

Every table of the book that comes from several training runs prints ``mean ± std`` over the
seeds with :func:`summarize_seeds`; a row from one run has no interval and says so.
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Iterable, Sequence
from pathlib import Path

__all__ = ["mean_std", "read_jsonl", "summarize_seeds"]


def mean_std(values: Iterable[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (``nan`` for a single value)."""
    vals = [float(v) for v in values]
    if not vals:
        raise ValueError("mean_std needs at least one value")
    return statistics.fmean(vals), (statistics.stdev(vals) if len(vals) > 1 else float("nan"))


def read_jsonl(path: str | Path, **match) -> list[dict]:
    """The JSON lines of ``path`` whose keys equal ``match`` (all lines if none given)."""
    lines = [json.loads(x) for x in Path(path).read_text().splitlines() if x.strip()]
    rows = [x for x in lines if all(x.get(k) == v for k, v in match.items())]
    if not rows:
        raise ValueError(f"{path} holds no lines with {match}")
    return rows


def summarize_seeds(
    rows: Sequence[dict], by: str | Sequence[str], metrics: Sequence[str]
) -> list[dict]:
    """One row per value of ``by`` (a key or keys), in order of appearance, with ``n_seeds`` and
    ``(mean, std)`` over the rows of each metric, for :func:`minimdm.utils.format_table`."""
    keys = (by,) if isinstance(by, str) else tuple(by)
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r.get(k) for k in keys), []).append(r)
    out = []
    for group, rs in groups.items():
        row = dict(zip(keys, group, strict=True))
        row["n_seeds"] = len({r.get("seed") for r in rs})
        row.update({m: mean_std(r[m] for r in rs) for m in metrics})
        out.append(row)
    return out
