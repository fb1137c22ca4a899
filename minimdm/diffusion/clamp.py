"""The clamp of the clean estimate: none, symmetric, or the training data's per-feature range."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from .schedule import ClipX0, X0Hook, check_finite


def clip_bounds(
    clip_x0: ClipX0,
    dim: int,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> float | tuple[Tensor, Tensor] | None:
    """Check a ``clip_x0`` setting and return it as ``None``, a float or ``(lo, hi)`` tensors.

    ``clip_x0`` is one of

    * ``None``: no clamp;
    * a float ``c > 0``: the symmetric box ``[-c, c]`` (explicit or legacy);
    * a pair ``(lo, hi)`` of length-``dim`` sequences or tensors, ``lo <= hi``: a per-feature
      box in normalized units, normally the training data's range (:func:`data_range`). A
      nested list ``[[lo...], [hi...]]`` (a checkpoint's JSON) or a ``(2, dim)`` tensor is such
      a pair.

    The tensors come back with ``dtype`` on ``device``, shape ``(dim,)`` each.
    """
    if clip_x0 is None:
        return None
    if isinstance(clip_x0, Tensor) and clip_x0.dim() == 0:
        clip_x0 = float(clip_x0)
    if isinstance(clip_x0, (int, float)) and not isinstance(clip_x0, bool):
        c = float(clip_x0)
        if not math.isfinite(c) or c <= 0:
            raise ValueError(f"clip_x0 must be a finite float > 0, got {clip_x0!r}")
        return c
    expected = f"None, a float > 0 or a pair (lo, hi) of {dim} values each"
    if isinstance(clip_x0, (str, bytes, bool)):
        hint = " ('data' is resolved by training from its frames)" if clip_x0 == "data" else ""
        raise ValueError(f"clip_x0 must be {expected}, got {clip_x0!r}{hint}")
    try:
        lo, hi = clip_x0
        lo = torch.as_tensor(lo, dtype=dtype, device=device)
        hi = torch.as_tensor(hi, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"clip_x0 must be {expected}, got a {type(clip_x0).__name__}") from None
    if lo.shape != (dim,) or hi.shape != (dim,):
        raise ValueError(
            f"clip_x0 must be a pair (lo, hi) of {dim} values each (one per feature), got shapes "
            f"{tuple(lo.shape)} and {tuple(hi.shape)}"
        )
    if not (torch.isfinite(lo).all() and torch.isfinite(hi).all()):
        raise ValueError("clip_x0 must hold finite bounds, but (lo, hi) holds NaN/Inf")
    if (lo > hi).any():
        i = int((lo > hi).nonzero()[0])
        raise ValueError(f"clip_x0 must have lo <= hi, but feature {i} has {lo[i]} > {hi[i]}")
    return lo, hi


def clamp_x0(x0: Tensor, bounds: float | tuple[Tensor, Tensor] | None) -> Tensor:
    """Clamp a clean estimate (B, D) to the bounds of :func:`clip_bounds`."""
    if bounds is None:
        return x0
    if isinstance(bounds, float):
        return x0.clamp(-bounds, bounds)
    return x0.clamp(bounds[0], bounds[1])


def data_range(frames: Tensor | Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """The per-feature range ``(lo, hi)`` of ``frames`` (N, D) or a list of (F_i, D) arrays.

    Returned as float32 (D,) tensors, rounded outwards, so that clamping any of the frames to it
    changes nothing: :func:`clamp_share` of the same frames is 0.
    """
    x = _stack_frames(frames)
    lo, hi = x.amin(0), x.amax(0)  # (D,)
    lo32, hi32 = lo.float(), hi.float()
    inf = torch.tensor(math.inf)
    lo32 = torch.where(lo32.double() > lo.double(), torch.nextafter(lo32, -inf), lo32)
    hi32 = torch.where(hi32.double() < hi.double(), torch.nextafter(hi32, inf), hi32)
    return lo32, hi32


def clamp_share(clip_x0: ClipX0, frames: Tensor | Sequence[Tensor]) -> float:
    """The share of ``frames`` (N, D) with at least one feature outside the clamp ``clip_x0``.

    These frames cannot come out of a sampler that clamps its :math:`\\hat x_0` so; for the
    training frames it should be 0.
    """
    x = _stack_frames(frames).double()
    bounds = clip_bounds(clip_x0, x.shape[-1], x.device, torch.float64)
    if bounds is None:
        return 0.0
    outside = (clamp_x0(x, bounds) != x).any(-1)  # (N,)
    return float(outside.double().mean())


def _stack_frames(frames: Tensor | Sequence[Tensor]) -> Tensor:
    if isinstance(frames, (list, tuple)):
        frames = torch.cat([torch.as_tensor(a) for a in frames])
    x = torch.as_tensor(frames)
    if x.dim() < 2 or x.shape[0] == 0:
        raise ValueError(f"frames must have shape (N >= 1, D), got {tuple(x.shape)}")
    x = x.reshape(-1, x.shape[-1])
    check_finite("frames", x)
    return x


def clamp_hook(
    clip_x0: ClipX0, dim: int, device: torch.device | str | None = None, dtype=torch.float32
) -> X0Hook | None:
    """The clamp as a hook on :math:`\\hat x_0` (None when ``clip_x0`` is None)."""
    bounds = clip_bounds(clip_x0, dim, device, dtype)
    if bounds is None:
        return None
    return lambda t, x_t, x0_hat: clamp_x0(x0_hat, bounds)


# --------------------------------------------------------------------------------------------
# Step rules: how one reverse step uses the clean estimate
