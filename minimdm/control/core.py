"""What every control technique shares: its start, the model's noise, the result.

The techniques steer a :class:`~minimdm.amdm.sampling.Sampler` (the model and everything
sampling a frame needs, read from a checkpoint as :func:`~minimdm.amdm.sampling.rollout` reads
it). Its :meth:`~minimdm.amdm.sampling.Sampler.frame` draws one frame through the one reverse
chain of :mod:`minimdm.diffusion`; the techniques differ only in the hook and the start of the
chain they hand it. :func:`as_start` checks what they start from, :func:`regressor_noise` gives
the MSE baseline a likelihood to sample, and :class:`Motion` is what they return.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from minimdm.amdm.models import MLPRegressor
from minimdm.amdm.sampling import Sampler
from minimdm.checkpoint import Checkpoint
from minimdm.motion.features import (
    Normalizer,
    StartPose,
    decode,
    decode_root,
    start_state,
)
from minimdm.validate import (
    check_frames,
    check_generator,
    check_int,
)

__all__ = ["regressor_noise", "as_start", "Motion"]


@torch.no_grad()
def regressor_noise(checkpoint: Checkpoint, clips: Any) -> Tensor:
    """Per-dimension residual std (D,) of a regressor on ``clips``, in normalized units.

    MSE training fits :math:`\\mathcal N(f(x_{f-1}), \\sigma^2 I)`; this is the maximum
    likelihood :math:`\\sigma` per dimension, to pass as ``Sampler.load(..., noise=...)`` so
    that the deterministic baseline proposes distinct candidates (A-MDM §7.3.3 compares models
    under the same search).
    """
    from minimdm.motion.features import encode

    if not isinstance(checkpoint.model, MLPRegressor) or checkpoint.normalizer is None:
        raise ValueError("checkpoint must hold an MLPRegressor and its normalizer")
    norm = Normalizer.from_dict(checkpoint.normalizer)
    net = checkpoint.model
    res = []
    for c in clips:
        x = norm.normalize(encode(c)).to(next(net.parameters()).device)  # (F, D)
        res.append((net(x[:-1]) - x[1:]).cpu())
    return torch.cat(res).std(dim=0)


def as_start(
    cm: Sampler, start: Any, start_pose: Any = None, generator: Any = None
) -> tuple[Tensor, bool, StartPose]:
    """Check what a technique starts from: ``start`` (D,) or (B, D) in feature units, or a
    :class:`~minimdm.motion.data.Clip` to continue (:func:`~minimdm.motion.features.start_state`,
    which compares the skeleton and frame rate it came from with the model's), its
    ``start_pose`` and the ``generator``.

    Returns:
        ``(x, batched, start_pose)``: x (B, D) float32 on the model's device, whether ``start``
        was batched, and a :class:`StartPose` with xy (B, 2) and heading (B,) float64.
    """
    check_generator("generator", generator, cm.device)
    start, start_pose = start_state(
        start, start_pose, skeleton=cm.skeleton, layout=cm.layout, name="start"
    )
    D = cm.dim
    joints = cm.layout.joint_names if cm.layout is not None else None
    x = check_frames("start", start, D, joints=joints)
    batched = x.dim() == 2
    if x.dim() == 1:
        x = x[None]
    return x.to(cm.device), batched, StartPose.broadcast(start_pose, x.shape[0])


def check_count(name: str, value: Any, minimum: int = 1) -> int:
    """:func:`minimdm.validate.check_int` with a lower bound: an integer >= ``minimum``."""
    return check_int(name, value, low=minimum)


@dataclass
class Motion:
    """A controlled motion of F frames x_1..x_F (x_0 is the start state).

    Leading dimensions mirror ``start``: with one start state (D,) the fields are per frame,
    e.g. ``positions`` is (F, J, 3); with a batch (B, D) they gain a leading B.
    """

    features: Tensor
    """([B,] F, D) frames in feature units (``minimdm.motion.features.encode``)."""
    normalized: Tensor
    """([B,] F, D) the same frames in the model's normalized space."""
    positions: Tensor
    """([B,] F, J, 3) global joint positions in metres, z-up."""
    root_xy: Tensor
    """([B,] F, 2) root ground positions in metres."""
    heading: Tensor
    """([B,] F) root headings in radians."""
    start_pose: StartPose
    """Root ground position and heading at the start state, where decoding starts."""
    info: dict[str, Any] = field(default_factory=dict)
    """Technique-specific extras (scores, frames done, t_start per frame...)."""

    @property
    def n_frames(self) -> int:
        return self.features.shape[-2]

    def numpy(self) -> np.ndarray:
        """The global joint positions as a numpy array, ([B,] F, J, 3)."""
        return self.positions.numpy()

    @classmethod
    def from_normalized(
        cls,
        cm: Sampler,
        normalized: Tensor,
        start_pose: StartPose,
        batched: bool,
        info: dict[str, Any] | None = None,
        features: Tensor | None = None,
    ) -> Motion:
        """Denormalize ``normalized`` (B, F, D), decode it from ``start_pose`` (B), squeeze."""
        normalized = normalized.detach().float().cpu()
        if features is None:
            features = cm.denormalize(normalized)
        f64 = features.double()
        sp = StartPose(start_pose.xy.cpu(), start_pose.heading.cpu())
        positions = decode(f64, sp).float()  # (B, F, J, 3)
        xy, heading = decode_root(f64, sp)  # (B, F, 2), (B, F)
        out = [normalized, features.float(), positions, xy.float(), heading.float()]
        if not batched:
            out = [t[0] for t in out]
            sp = StartPose(sp.xy[0], sp.heading[0])
        return cls(out[1], out[0], out[2], out[3], out[4], sp, dict(info or {}))
