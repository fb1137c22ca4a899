"""Residual steering of the denoising chain (A-MDM §5.2, eq. 7), as a hook of the one sampler.

For frame f the policy outputs residuals :math:`a_f = \\{a_f^T, \\dots, a_f^1\\}`; each perturbs
the output of one denoising step,

.. math:: \\tilde x_{f+1}^t = \\hat x_{f+1}^t + w^t a_f^t, \\qquad (7)

and the perturbed sample is the input of the next step. :class:`ResidualSchedule` says which
steps receive a residual, on which features, and with which weight :math:`w^t`;
:func:`residual_hook` turns one frame's actions into a hook for
:func:`minimdm.diffusion.reverse_chain` (through any sampler's ``hook=``).

Levels follow :mod:`minimdm.diffusion`: 0-based, the step *from* level ``t`` leaves the chain at
``t - 1`` (``-1``: the clean frame). The paper's step t (1-based) is our level ``t - 1``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from minimdm.diffusion import Hook
from minimdm.motion.features import FeatureLayout

__all__ = ["ResidualSchedule", "residual_hook", "feature_indices", "ANNEALING"]

ANNEALING = ("linear", "cosine", "none")
"""The shapes of :math:`w^t` over the perturbed steps (see :meth:`ResidualSchedule.weights`)."""


def feature_indices(layout: FeatureLayout, features: str) -> list[int]:
    """The frame dimensions a residual acts on.

    ``"all"``: every feature (the paper's full residual, D per step); ``"root"``: the root's
    planar velocity and yaw rate (3 per step: forward, left, yaw). With ``"root"`` the policy
    pushes where the root goes and the remaining denoising steps make a body that fits it.
    """
    if features == "all":
        return list(range(layout.dim))
    if features == "root":
        return [*range(layout.root_vel.start, layout.root_vel.stop), layout.yaw_rate.start]
    raise ValueError(f"features must be 'all' or 'root', got {features!r}")


@dataclass(frozen=True)
class ResidualSchedule:
    """Which denoising steps receive a residual, and with what weight (eq. 7).

    Args:
        T: the base model's number of diffusion steps.
        levels: the 0-based levels whose step output is perturbed, noisiest first (e.g.
            ``range(T - 1, 3, -1)`` leaves the last four steps to the model alone).
        anneal: the shape of :math:`w^t`, falling from 1 at the noisiest perturbed level
            towards 0 after the least noisy one: with the K perturbed levels numbered i = K..1
            noisiest first, ``"linear"`` :math:`w = i / K`, ``"cosine"`` :math:`w =
            (1 - \\cos(\\pi i / K)) / 2` (an S that is flat at both ends), ``"none"`` 1 everywhere
            (the ablation: large late residuals leave artefacts).
        scale: a factor on every weight (the action's unit, in standard deviations of the
            normalized features).
        tied: one residual :math:`a` for all K steps, :math:`a^t = a` (K times fewer action
            dimensions; :math:`w^t` still anneals it), instead of one per step.
    """

    T: int
    levels: tuple[int, ...]
    anneal: str = "linear"
    scale: float = 1.0
    tied: bool = False

    def __post_init__(self) -> None:
        levels = tuple(int(t) for t in self.levels)
        object.__setattr__(self, "levels", levels)
        if not levels:
            raise ValueError("levels must name at least one denoising level")
        if any(not 0 <= t < self.T for t in levels):
            raise ValueError(f"levels must lie in [0, T-1={self.T - 1}], got {list(levels)}")
        if any(a <= b for a, b in zip(levels[:-1], levels[1:], strict=True)):
            raise ValueError(f"levels must be strictly decreasing (noisiest first), got {levels}")
        if self.anneal not in ANNEALING:
            raise ValueError(f"anneal must be one of {ANNEALING}, got {self.anneal!r}")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"scale must be a positive number, got {self.scale}")

    @classmethod
    def top(
        cls, T: int, n: int, anneal: str = "linear", scale: float = 1.0, tied: bool = False
    ) -> ResidualSchedule:
        """The ``n`` noisiest levels, ``T - 1`` down to ``T - n``."""
        if not 1 <= n <= T:
            raise ValueError(f"n must lie in [1, T={T}], got {n}")
        return cls(T, tuple(range(T - 1, T - 1 - n, -1)), anneal, scale, tied)

    @property
    def n_steps(self) -> int:
        """K, the number of perturbed steps."""
        return len(self.levels)

    @property
    def n_residuals(self) -> int:
        """Residual vectors per frame: 1 when tied, else K."""
        return 1 if self.tied else self.n_steps

    def weights(self) -> Tensor:
        """(K,) :math:`w^t` for ``levels`` (noisiest first), float32."""
        K = self.n_steps
        i = torch.arange(K, 0, -1, dtype=torch.float64)  # K .. 1, noisiest first
        if self.anneal == "linear":
            w = i / K
        elif self.anneal == "cosine":
            w = 0.5 * (1 - torch.cos(math.pi * i / K))
        else:
            w = torch.ones(K, dtype=torch.float64)
        return (self.scale * w).float()

    def weight_of(self) -> dict[int, float]:
        """``{level: w^t}`` for the perturbed levels."""
        return dict(zip(self.levels, self.weights().tolist(), strict=True))

    def to_dict(self) -> dict:
        return {
            "T": self.T,
            "levels": list(self.levels),
            "anneal": self.anneal,
            "scale": self.scale,
            "tied": self.tied,
        }

    @classmethod
    def from_dict(cls, d: dict) -> ResidualSchedule:
        return cls(
            int(d["T"]),
            tuple(d["levels"]),
            d.get("anneal", "linear"),
            d.get("scale", 1.0),
            bool(d.get("tied", False)),
        )


def residual_hook(
    schedule: ResidualSchedule,
    actions: Tensor,
    chain_levels: Sequence[int],
    features: Sequence[int] | None = None,
    units: Tensor | None = None,
) -> Hook:
    """The hook that adds one frame's residuals to the chain (eq. 7).

    Args:
        schedule: which levels and weights.
        actions: (B, K, F) residuals :math:`a^t`, one row per perturbed level (noisiest
            first), on ``F`` features; (B, K * F) is reshaped. A tied schedule takes (B, F)
            (or (B, 1, F)): the same residual at every perturbed level.
        chain_levels: the levels the sampler visits, noisiest first (``range(T - 1, -1, -1)``
            for DDPM, the DDIM grid otherwise). The hook is told the level the chain moves to;
            this list says which step got it there. A perturbed level the chain skips raises.
        features: the frame dimensions the residuals act on (default: all D).
        units: (F,) the chain's units per unit of the normalized frame, one per feature, a
            factor on every residual (default 1). A delta model's chain denoises the change
            ``z = (x - x_{f-1}) / k`` (:meth:`~minimdm.amdm.models.MLPDenoiser.to_delta`): with
            ``units = 1 / k`` a residual keeps the meaning it has for a model of the frame, a
            push of so many standard deviations of the feature.

    Returns:
        ``hook(t_next, x, x0_hat) -> x``: after the step from a perturbed level ``t`` it returns
        ``x + w^t a^t`` on ``features``; after any other step, ``x`` unchanged.

    Raises:
        ValueError: actions of the wrong shape or holding NaN/Inf.
    """
    chain_levels = [int(t) for t in chain_levels]
    missing = sorted(set(schedule.levels) - set(chain_levels), reverse=True)
    if missing:
        raise ValueError(f"the chain never steps from the perturbed levels {missing}")
    actions = torch.as_tensor(actions)
    K = schedule.n_residuals
    if actions.dim() == 2 and actions.shape[1] % K == 0:
        actions = actions.reshape(actions.shape[0], K, -1)
    F = len(features) if features is not None else None
    if actions.dim() != 3 or actions.shape[1] != K or (F is not None and actions.shape[2] != F):
        want = f"(B, {K}, {F if F is not None else 'D'})"
        raise ValueError(f"actions must have shape {want} or (B, K*F), got {tuple(actions.shape)}")
    if not torch.isfinite(actions).all():
        raise ValueError("actions must be finite, but they hold NaN/Inf")
    if schedule.tied:
        actions = actions.expand(-1, schedule.n_steps, -1)
    after = {  # the level the chain reaches after stepping from t -> index of t in the schedule
        (chain_levels[i + 1] if i + 1 < len(chain_levels) else -1): schedule.levels.index(t)
        for i, t in enumerate(chain_levels)
        if t in schedule.levels
    }
    w = schedule.weights().to(actions.device, actions.dtype)  # (K,)
    idx = None if features is None else torch.as_tensor(list(features), device=actions.device)
    if units is not None:
        units = torch.as_tensor(units, device=actions.device, dtype=actions.dtype)
        if units.shape != (actions.shape[2],) or not (
            torch.isfinite(units).all() and (units > 0).all()
        ):
            raise ValueError(
                f"units must hold {actions.shape[2]} positive finite factors, one per feature, "
                f"got shape {tuple(units.shape)}"
            )
        actions = actions * units

    def hook(t_next: int, x: Tensor, x0_hat: Tensor) -> Tensor:
        k = after.get(t_next)
        if k is None:
            return x
        delta = w[k] * actions[:, k].to(x.dtype)  # (B, F)
        if idx is None:
            return x + delta
        return x.index_add(1, idx, delta)

    return hook
