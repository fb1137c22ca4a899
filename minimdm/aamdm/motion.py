"""AAMDM on motion (Qiao et al. 2024, §3.1, §3.4-3.6): an embedded space, DD-GAN + polishing in it.

A pose is the A-MDM frame ``y`` (:mod:`minimdm.motion.features`, 183 numbers for the humanoid).
AAMDM
replaces it by a compact embedded vector ``xz`` (§3.1):

* ``x`` (12): engineered **future-trajectory features** (§3.6), the root's ground position and
  facing direction ``horizons`` frames ahead (default 10, 20, 30 frames = 1/3, 2/3, 1 s at
  30 Hz, LMM's 20/40/60 frames at 60 Hz), in the character's heading frame; positions (2 each)
  then directions (cos, sin each). Near the end of a clip the last frame stands in for the
  missing future;
* ``z`` (``z_dim``): a latent learned by an autoencoder, :math:`E^{AE}(y) \\to z` and
  :math:`D^{AE}(xz) \\to \\hat y`, trained with eqs. 1-4: feature and forward-kinematics errors
  (:math:`L_{val}`), FK velocity errors over two consecutive frames (:math:`L_{vel}`), and
  :math:`\\|z\\|^2` (:math:`L_{reg}`).

The transition :math:`xz_{n-1} \\to xz_n` is an :class:`~minimdm.aamdm.model.AAMDM` (3 DD-GAN steps
and
2 polishing steps) over the standardised ``xz``; a frame is sampled in the latent space and
decoded to a pose. :class:`AAMDMMotion` holds the three networks and every normalisation, and is
one checkpoint (kind ``"aamdm_motion"``). Training is :func:`train_aamdm_motion`; its command
line is ``python -m minimdm.aamdm train configs/aamdm.yaml``
(:mod:`minimdm.aamdm.motion_train`). Rollouts, guidance (eq. 13)
and the evaluation live in :mod:`minimdm.aamdm.eval`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from minimdm.aamdm.model import AAMDM, AAMDMConfig
from minimdm.checkpoint import register_model_kind
from minimdm.motion.skeleton import (
    Skeleton,
    heading_angle,
    sixd_to_matrix,
    to_heading_frame,
    wrap_angle,
)
from minimdm.nn import MLP

__all__ = [
    "trajectory_features",
    "clip_trajectory_features",
    "fk_positions",
    "PoseAutoencoder",
    "autoencoder_loss",
    "MotionModelConfig",
    "AAMDMMotion",
]

X_DIM = 12
"""Size of the engineered features x: 3 future positions (2) and 3 future directions (2)."""


# --------------------------------------------------------------------------------------------
# The engineered features x (§3.6) and forward kinematics F (eqs. 1-2)


def trajectory_features(
    root_xy: Tensor, heading: Tensor, horizons: tuple[int, ...] = (10, 20, 30)
) -> Tensor:
    """Future root positions and facing directions in each frame's heading frame.

    Args:
        root_xy: ``(F, 2)`` root ground positions; heading: ``(F,)`` radians.
        horizons: frames ahead; a future past the last frame uses the last frame.

    Returns:
        ``(F, 4 * len(horizons))``: the positions ``(dx, dy)`` of every horizon, then the
        directions ``(cos, sin)`` of the heading change to every horizon.
    """
    F = root_xy.shape[0]
    idx = torch.arange(F)
    pos, dirs = [], []
    for h in horizons:
        g = (idx + int(h)).clamp(max=F - 1)
        d = root_xy[g] - root_xy  # (F, 2) world
        pos.append(to_heading_frame(d, heading))
        a = wrap_angle(heading[g] - heading)
        dirs.append(torch.stack([torch.cos(a), torch.sin(a)], -1))
    return torch.cat(pos + dirs, dim=-1)


def clip_trajectory_features(clip: Any, horizons: tuple[int, ...] = (10, 20, 30)) -> Tensor:
    """x for the rows of ``features.encode(clip)`` (clip frames 1..F-1): ``(F - 1, 12)``."""
    _, rot = clip.fk()
    heading = heading_angle(rot[:, 0], clip.skeleton.lateral_axis)
    xy = torch.as_tensor(clip.root_pos[:, :2], dtype=torch.float64)
    return trajectory_features(xy, heading, horizons)[1:].float()


def fk_positions(features: Tensor, skeleton: Skeleton) -> Tensor:
    """F(y): joint positions from the rotations of frames ``(..., D)``, ``(..., J, 3)``.

    Forward kinematics on the global rotations ``j_o`` (6D, heading frame) and the skeleton's
    offsets, from the root position of ``j_p``: :math:`p_j = p_{parent} + R_{parent}\\,o_j`.
    Differentiable; for data it reproduces ``j_p`` (the rotations and positions agree).
    """
    J = len(skeleton)
    root = features[..., 3:6]  # (..., 3) the root in its heading frame
    R = sixd_to_matrix(
        features[..., 3 + 6 * J : 3 + 12 * J].unflatten(-1, (J, 6))
    )  # (..., J, 3, 3)
    offsets = torch.as_tensor(skeleton.offsets, dtype=features.dtype, device=features.device)
    pos = [root]
    for j in range(1, J):
        p = skeleton.parents[j]
        pos.append(pos[p] + (R[..., p, :, :] @ offsets[j, :, None])[..., 0])
    return torch.stack(pos, dim=-2)


# --------------------------------------------------------------------------------------------
# The autoencoder (§3.1)


class PoseAutoencoder(nn.Module):
    """:math:`E^{AE}(y) \\to z` and :math:`D^{AE}(x, z) \\to \\hat y`, on normalized frames."""

    def __init__(self, y_dim: int, x_dim: int, z_dim: int, width: int, depth: int) -> None:
        super().__init__()
        self.y_dim, self.x_dim, self.z_dim = y_dim, x_dim, z_dim
        self.encoder = MLP(y_dim, z_dim, width, depth).sequential()
        self.decoder = MLP(x_dim + z_dim, y_dim, width, depth).sequential()

    def encode(self, y: Tensor) -> Tensor:
        if y.shape[-1] != self.y_dim:
            raise ValueError(f"y must have last dim {self.y_dim}, got shape {tuple(y.shape)}")
        return self.encoder(y)

    def decode(self, xz: Tensor) -> Tensor:
        if xz.shape[-1] != self.x_dim + self.z_dim:
            raise ValueError(
                f"xz must have last dim x_dim + z_dim = {self.x_dim} + {self.z_dim}, "
                f"got shape {tuple(xz.shape)}"
            )
        return self.decoder(xz)


def autoencoder_loss(
    ae: PoseAutoencoder,
    y: Tensor,
    x: Tensor,
    denormalize,
    skeleton: Skeleton,
    w_val: float = 1.0,
    w_vel: float = 1.0,
    w_reg: float = 0.01,
    fk_scale: float = 10.0,
) -> tuple[Tensor, dict[str, float]]:
    """AAMDM eqs. 1-4 on pairs of consecutive frames ``y (B, 2, D)``, ``x (B, 2, 12)`` (normalized).

    * :math:`L_{val} = \\|\\hat y - y\\|^2 + \\|F(\\hat y) - F(y)\\|^2` (eq. 1), the feature error
      in normalized units plus the FK position error (``fk_scale`` 10: in decimetres, so that a
      1 cm error weighs 0.01);
    * :math:`L_{vel} = \\|(F(\\hat y_1) - F(\\hat y_0)) - (F(y_1) - F(y_0))\\|^2` (eq. 2, per
      frame, same units);
    * :math:`L_{reg} = \\|z\\|^2` (eq. 3), averaged over dimensions;
    * :math:`L = w_{val} L_{val} + w_{vel} L_{vel} + w_{reg} L_{reg}` (eq. 4).
    """
    z = ae.encode(y)  # (B, 2, Z)
    y_hat = ae.decode(torch.cat([x, z], dim=-1))  # (B, 2, D)
    f_hat = fk_positions(denormalize(y_hat), skeleton) * fk_scale  # (B, 2, J, 3)
    f = fk_positions(denormalize(y), skeleton) * fk_scale
    l_feat = ((y_hat - y) ** 2).mean()
    l_fk = ((f_hat - f) ** 2).sum(-1).mean()
    l_vel = (((f_hat[:, 1] - f_hat[:, 0]) - (f[:, 1] - f[:, 0])) ** 2).sum(-1).mean()
    l_reg = (z**2).mean()
    loss = w_val * (l_feat + l_fk) + w_vel * l_vel + w_reg * l_reg
    info = {
        "l_feat": l_feat.item(),
        "l_fk": l_fk.item(),
        "l_vel": l_vel.item(),
        "l_reg": l_reg.item(),
    }
    return loss, info


# --------------------------------------------------------------------------------------------
# The whole model


@dataclass
class MotionModelConfig:
    """Sizes of an :class:`AAMDMMotion`; stored in its checkpoint."""

    y_dim: int
    """Dimension of a pose y (the A-MDM frame)."""
    x_dim: int = X_DIM
    """Dimension of the engineered features x."""
    z_dim: int = 24
    """Dimension of the learned latent z (paper: 52 for a 338-dim pose)."""
    ae_width: int = 256
    """Hidden units of the encoder and the decoder."""
    ae_depth: int = 3
    """Layers of the encoder and the decoder."""
    horizons: list[int] = field(default_factory=lambda: [10, 20, 30])
    """Frames ahead of the future-trajectory features."""
    transition: dict = field(default_factory=dict)
    """The AAMDMConfig of the transition model, as a dict."""


class AAMDMMotion(nn.Module):
    """Autoencoder + AAMDM transition + normalisations (buffers), one checkpoint.

    Spaces: ``y`` features (A-MDM units), ``y_n`` normalized features, ``x_n`` normalized x,
    ``xz_raw = (x_n, z)`` the autoencoder's embedding, ``xz`` its standardisation, where the
    transition model works.
    """

    def __init__(self, config: MotionModelConfig) -> None:
        super().__init__()
        self.config = c = config
        self.autoencoder = PoseAutoencoder(c.y_dim, c.x_dim, c.z_dim, c.ae_width, c.ae_depth)
        tcfg = AAMDMConfig(**c.transition)
        if tcfg.x_dim != c.x_dim + c.z_dim or tcfg.cond_dim != c.x_dim + c.z_dim:
            raise ValueError(
                f"the transition model must work on xz of size x_dim + z_dim = {c.x_dim} + "
                f"{c.z_dim} = {c.x_dim + c.z_dim}, got x_dim {tcfg.x_dim} and cond_dim "
                f"{tcfg.cond_dim}"
            )
        self.transition = AAMDM(tcfg)
        for name, dim in (("y", c.y_dim), ("x", c.x_dim), ("xz", c.x_dim + c.z_dim)):
            self.register_buffer(f"{name}_mean", torch.zeros(dim))
            self.register_buffer(f"{name}_std", torch.ones(dim))

    @property
    def xz_dim(self) -> int:
        return self.config.x_dim + self.config.z_dim

    def encode(self, y: Tensor, x: Tensor) -> Tensor:
        """Pose features ``y (..., D)`` and engineered ``x (..., 12)`` to standardised xz."""
        z = self.autoencoder.encode((y - self.y_mean) / self.y_std)
        xz_raw = torch.cat([(x - self.x_mean) / self.x_std, z], dim=-1)
        return (xz_raw - self.xz_mean) / self.xz_std

    def decode(self, xz: Tensor) -> Tensor:
        """Standardised ``xz (..., X + Z)`` to pose features ``y (..., D)`` (A-MDM units)."""
        y_n = self.autoencoder.decode(xz * self.xz_std + self.xz_mean)
        return y_n * self.y_std + self.y_mean

    def x_of(self, xz: Tensor) -> Tensor:
        """The engineered features x (physical units) inside standardised ``xz``."""
        X = self.config.x_dim
        x_n = xz[..., :X] * self.xz_std[:X] + self.xz_mean[:X]
        return x_n * self.x_std + self.x_mean

    def config_dict(self) -> dict:
        return asdict(self.config)


register_model_kind(
    "aamdm_motion",
    AAMDMMotion,
    lambda c: AAMDMMotion(MotionModelConfig(**c)),
    lambda m: m.config_dict(),
)
