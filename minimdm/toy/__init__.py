"""Toy data, chapters 1 and 8: Squ-9, the 2D many-to-many transition set of AAMDM §4.2."""

from .squ9 import (
    Squ9,
    plot_transition_matrix,
    plot_transitions,
    squ9_metrics,
    train_denoiser,
    train_regressor,
)

__all__ = [
    "Squ9",
    "squ9_metrics",
    "plot_transitions",
    "plot_transition_matrix",
    "train_denoiser",
    "train_regressor",
]
