"""Figures of the acceleration chapter: the Squ-9 panels.

:func:`plot_panels` draws AAMDM Figure 3 (one transition plot per method). The chapter's tables
are printed by :func:`minimdm.utils.format_table`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from minimdm.studies.squ9_acceleration import LABELS, PANELS
from minimdm.toy.squ9 import Squ9, plot_transitions

__all__ = ["plot_panels"]


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
            center = sq.mode_centers[source]
            ax.scatter(*center, marker="*", s=180, facecolors="none", c="none", edgecolors="k")
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
