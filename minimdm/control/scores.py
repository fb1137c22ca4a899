"""Score functions for :func:`~minimdm.control.beam_search` (A-MDM §4.2). Higher is better.

Each factory returns ``score(future) -> (b, P)`` for a :class:`~minimdm.control.beam.Future`
of b characters, P candidates and H frames. Goals may be one for all characters or one per
character (``goal[future.index]`` picks the searching ones). Any callable with that signature
works; :func:`combine` adds weighted scores.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from .beam import Future

__all__ = ["target_score", "heading_score", "speed_score", "combine", "reached"]

Score = Callable[[Future], Tensor]


def _per_character(name: str, value: Any, trailing: tuple[int, ...]) -> Tensor:
    """``value`` as float64 (B or 1, *trailing), checked finite."""
    v = torch.as_tensor(value, dtype=torch.float64)
    if tuple(v.shape[v.dim() - len(trailing) :]) != trailing or v.dim() > len(trailing) + 1:
        want = f"{trailing} or (B, {', '.join(map(str, trailing))})" if trailing else "() or (B,)"
        raise ValueError(f"{name} must have shape {want}, got {tuple(v.shape)}")
    if not torch.isfinite(v).all():
        raise ValueError(f"{name} must be finite, got {v.tolist()}")
    return v.reshape(-1, *trailing)


def _pick(v: Tensor, future: Future) -> Tensor:
    return v[0].expand(len(future.index), *v.shape[1:]) if v.shape[0] == 1 else v[future.index]


def target_score(goal: Any, reduce: str = "last") -> Score:
    """Target reaching (A-MDM §6.1, §7.3.3): minus the 2D root distance to ``goal``.

    Args:
        goal: (2,) or (B, 2) target on the ground, metres.
        reduce: ``"last"``: the distance at the end of the horizon (with H = 1, the paper's
            score); ``"min"``: the closest the candidate comes within the horizon.
    """
    g = _per_character("goal", goal, (2,))
    if reduce not in ("last", "min"):
        raise ValueError(f"reduce must be 'last' or 'min', got {reduce!r}")

    def score(future: Future) -> Tensor:
        d = (future.root_xy - _pick(g, future)[:, None, None]).norm(dim=-1)  # (b, P, H)
        return -(d[..., -1] if reduce == "last" else d.min(dim=-1).values)

    return score


def heading_score(direction: Any) -> Score:
    """Face a direction: the mean over the horizon of :math:`\\cos(h - h^*)`, in [-1, 1].

    Args:
        direction: (,) or (B,) desired heading in radians (0: +x, pi/2: +y).
    """
    d = _per_character("direction", direction, ())

    def score(future: Future) -> Tensor:
        return torch.cos(future.heading - _pick(d, future)[:, None, None]).mean(dim=-1)

    return score


def speed_score(speed: Any) -> Score:
    """Move at a speed: minus the mean over the horizon of :math:`|\\,\\|v\\| - v^*|` (m/s).

    Args:
        speed: (,) or (B,) desired planar root speed in m/s.
    """
    s = _per_character("speed", speed, ())
    if (s < 0).any():
        raise ValueError(f"speed must be >= 0, got {s.tolist()}")

    def score(future: Future) -> Tensor:
        v = future.velocity.norm(dim=-1)  # (b, P, H)
        return -(v - _pick(s, future)[:, None, None]).abs().mean(dim=-1)

    return score


def combine(*terms: Score | tuple[float, Score]) -> Score:
    """The weighted sum of scores; each term is a score or a ``(weight, score)`` pair."""
    if not terms:
        raise ValueError("combine needs at least one score")
    pairs: Sequence[tuple[float, Score]] = [t if isinstance(t, tuple) else (1.0, t) for t in terms]
    for i, (_, fn) in enumerate(pairs):
        if not callable(fn):
            raise ValueError(f"term {i} must be a score function, got {type(fn).__name__}")

    def score(future: Future) -> Tensor:
        return sum(float(w) * fn(future) for w, fn in pairs)

    return score


def reached(goal: Any, radius: float = 0.15) -> Callable[[Future], Tensor]:
    """A ``stop_fn``: True once the root is within ``radius`` (A-MDM §6.1: 15 cm) of ``goal``."""
    g = _per_character("goal", goal, (2,))
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")

    def stop(future: Future) -> Tensor:
        return (future.root_xy[:, 0, -1] - _pick(g, future)).norm(dim=-1) <= radius

    return stop
