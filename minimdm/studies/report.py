"""Tables and figures of the acceleration chapter: fixed-width tables, the Squ-9 panels.

:func:`format_table` prints the rows of
:meth:`minimdm.studies.squ9_acceleration.Squ9Study.evaluate`,
:meth:`~minimdm.studies.squ9_acceleration.Squ9Study.ablation` or
:func:`minimdm.aamdm.eval.motion_comparison`;
:func:`plot_panels` draws AAMDM Figure 3 (one transition plot per method).
"""

from __future__ import annotations

import torch
from torch import Tensor

from minimdm.studies.squ9_acceleration import LABELS, PANELS
from minimdm.toy.squ9 import Squ9, plot_transitions

__all__ = ["format_table", "plot_panels"]


def format_table(rows: list[dict], keys: tuple[str, ...] | None = None) -> str:
    """A fixed-width text table of ``rows`` (the dicts of :meth:`Squ9Study.evaluate`)."""
    keys = keys or tuple(k for k in rows[0] if k not in ("method",))
    width = {k: max(len(k), *(len(_fmt(r.get(k))) for r in rows)) for k in keys}
    head = "  ".join(k.rjust(width[k]) if k != "label" else k.ljust(width[k]) for k in keys)
    lines = [head]
    for r in rows:
        cells = [
            _fmt(r.get(k)).ljust(width[k]) if k == "label" else _fmt(r.get(k)).rjust(width[k])
            for k in keys
        ]
        lines.append("  ".join(cells))
    return "\n".join(lines)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"
    return "-" if v is None else str(v)


def plot_panels(
    x_eval: Tensor,
    samples: dict,
    rows: list[dict] | None = None,
    keys: tuple = PANELS,
    titles: dict | None = None,
    ncols: int = 3,
    source: int | None = None,
):
    """A grid of transition plots, one panel per key of ``samples`` (AAMDM Figure 3).

    Every panel shows the sampled next points coloured by source mode; ``source`` keeps only the
    samples whose condition lies in that mode (the hollow star). Titles carry the metrics of
    ``rows`` when given. Returns the Figure.
    """
    import matplotlib.pyplot as plt

    sq = Squ9()
    nrows = -(-len(keys) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.3 * ncols, 3.4 * nrows), squeeze=False)
    by = {r.get("method", (r.get("T_gan"), r.get("T_adm"))): r for r in rows or []}
    keep = torch.ones(len(x_eval), dtype=torch.bool)
    if source is not None:
        keep = sq.mode_of(x_eval.cpu()) == source
    for ax, key in zip(axes.flat, keys, strict=False):
        x = samples[key]
        plot_transitions(x_eval.cpu()[keep], x.cpu()[keep], ax=ax, s=2 if source is None else 4)
        if source is not None:
            ax.scatter(*sq.mode_centers[source], marker="*", s=180, facecolors="none", c="none",
                       edgecolors="k")  # fmt: skip
        title = (titles or {}).get(key) or LABELS.get(key, str(key))
        r = by.get(key)
        if r:
            title += (
                f"\ncov {r['coverage']:.2f}  prec {r['precision']:.2f}  TV {r['transition_tv']:.2f}"
            )
        ax.set_title(title, fontsize=9)
    for ax in list(axes.flat)[len(keys) :]:
        ax.axis("off")
    fig.tight_layout()
    return fig
