"""The tables of chapter 4 (A-MDM §7.3): the steps sweep and the stored benchmark rows.

The protocol itself (initial states, metrics, Tables 1 and 2, timing, drift) is the library's
:mod:`minimdm.amdm.evaluation`; this module only arranges its results the way the chapter and
``benchmarks/amdm_tables.py`` show them:

* :func:`steps_table`, Tables 3/4: one model per number of denoising steps T, its Table 1
  metrics and its ms/frame at batch 1, measured in the same run;
* :func:`read_results`, the rows that ``benchmarks/amdm_tables.py --save`` wrote, ready for
  :func:`minimdm.utils.format_table`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import torch

from minimdm.amdm.evaluation import TABLE1_COLUMNS, Protocol, table1, time_per_frame
from minimdm.checkpoint import Checkpoint

__all__ = ["STEPS_COLUMNS", "steps_table", "read_results"]

STEPS_COLUMNS = ("APD", "ADE", "FS", "Bone.Err", "Jnt.Accel", "ms/frame")
"""The columns of the steps table (A-MDM Tables 3 and 4, plus bone error and jitter)."""


def steps_table(
    models: Mapping[str, Checkpoint],
    protocol: Protocol | None = None,
    *,
    device: torch.device | str = "cpu",
) -> dict[str, dict[str, tuple[float, float] | float]]:
    """Tables 3/4: the Table 1 metrics of every model plus ``"ms/frame"`` at batch 1.

    The models (one per T) start from the same initial states; the time is the median of
    :func:`~minimdm.amdm.evaluation.time_per_frame` in ms (a float, not a mean ± std).
    """
    table: dict[str, dict] = table1(models, protocol, device=device)
    for name, ck in models.items():
        table[name]["ms/frame"] = time_per_frame(ck, batch=1, device=device)
    return table


def read_results(
    path: str | Path, table: str, key: str | tuple[str, ...] = "model"
) -> dict[str, dict]:
    """Rows of one table from a JSON-lines file written by ``benchmarks/amdm_tables.py``.

    Args:
        path: the JSON-lines file.
        table: which table's rows (``"table1"``, ``"table2"``, ``"memorisation"``, ``"steps"``).
        key: the field that names a row (``"T"`` for the steps sweep), or several fields whose
            values are joined with ", " (``("model", "frames")`` for the memorisation probe,
            whose rows are "A-MDM, generated", "A-MDM, held-out", ...).

    Returns ``{row name: {metric: (mean, std)}}`` with the metrics in the order of Table 1,
    ready for :func:`minimdm.utils.format_table`.
    """
    keys = (key,) if isinstance(key, str) else tuple(key)
    out: dict[str, dict] = {}
    for line in Path(path).read_text().splitlines():
        rec = json.loads(line)
        if rec.get("table") != table:
            continue
        cells = {
            k: (v["mean"], v["std"])
            for k, v in rec.items()
            if isinstance(v, dict) and set(v) == {"mean", "std"}
        }
        order = [c for c in TABLE1_COLUMNS if c in cells]
        order += [c for c in cells if c not in TABLE1_COLUMNS]
        out[", ".join(str(rec.get(k)) for k in keys)] = {c: cells[c] for c in order}
    if not out:
        raise ValueError(f"{path} holds no rows of table {table!r}")
    return out
