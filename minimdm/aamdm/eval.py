"""Sampling the motion AAMDM, guiding its root direction (eq. 13) and comparing it with A-MDM.

:func:`rollout_aamdm` generates frames auto-regressively in the embedded space (one
:meth:`~minimdm.aamdm.model.AAMDM.sample` per frame, then the decoder) and returns the same
:class:`~minimdm.amdm.sampling.Rollout` as A-MDM's :func:`~minimdm.amdm.sampling.rollout`. With a
``direction`` it applies the guidance of AAMDM §3.5 (eq. 13): every step's clean estimate is
pushed down the gradient of the distance between the facing directions in :math:`\\hat x` and
the commanded one.

:func:`motion_quality` scores rollouts on the A-MDM chapter's metrics (APD, foot sliding, bone
length error, joint acceleration) plus two distribution measures in the spirit of AAMDM §4.1.1:
``DIV``, MDM's diversity (the mean distance between random pairs of generated poses, to be
compared with the data's), and ``FD``, a Fréchet distance between Gaussian fits of generated and
dataset poses (FID without an inception network: poses are root-relative joint positions in cm).

The harnesses that build the chapter's tables from these (the comparison with A-MDM, the
guidance study, the dataset row, frames per second) live in :mod:`minimdm.studies.aamdm_motion`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from minimdm.aamdm.model import Guide
from minimdm.aamdm.motion import AAMDMMotion
from minimdm.amdm.sampling import Rollout, autoregress
from minimdm.checkpoint import check_same_model
from minimdm.diffusion import NoiseTape
from minimdm.motion import metrics
from minimdm.motion.features import StartPose, decode, start_pose_of
from minimdm.motion.skeleton import wrap_angle

__all__ = [
    "INITIAL_CLIPS",
    "initial_states",
    "direction_guide",
    "aamdm_frame",
    "rollout_aamdm",
    "local_poses",
    "pose_diversity",
    "pose_frechet_distance",
    "motion_quality",
    "heading_tracking_error",
]

INITIAL_CLIPS = (
    "walk",
    "run",
    "walker/turn_left0",
    "walker/turn_right1",
    "dance_a",
    "jump",
    "punch",
    "spin",
)
"""Clips whose frame ``frame`` starts the evaluation rollouts (locomotion and other skills)."""


def initial_states(
    data: dict, names: tuple[str, ...] | None = None, row: int = 10
) -> dict[str, Any]:
    """Initial frames from :func:`~minimdm.aamdm.load_motion_data`'s ``data``.

    Returns ``y`` (C, D) and ``x`` (C, 12) of feature row ``row`` of each named clip, the
    ``start`` pose (root ground position and heading at that frame) that decoding starts from,
    and each clip's ``bone_lengths`` (C, J - 1). ``names`` default to :data:`INITIAL_CLIPS` for
    the DeepMimic clips and to every clip otherwise (e.g. a corpus's held-out takes).
    """
    clips = data["clips"]
    if names is None:
        names = INITIAL_CLIPS if set(INITIAL_CLIPS) <= set(clips.names) else tuple(clips.names)
    idx = [clips.names.index(n) for n in names]
    y = torch.stack([data["y"][i][row] for i in idx])
    x = torch.stack([data["x"][i][row] for i in idx])
    starts = [start_pose_of(clips[i], row + 1) for i in idx]  # row r is clip frame r + 1
    start = StartPose(
        torch.stack([s.xy for s in starts]),
        torch.stack([torch.as_tensor(s.heading) for s in starts]),
    )
    skeletons = [clips[i].skeleton for i in idx]  # each take's own actor: Bone.Err's reference
    bones = torch.stack(
        [torch.as_tensor(metrics.skeleton_bone_lengths(s.offsets, s.parents)) for s in skeletons]
    )
    return {"y": y, "x": x, "start": start, "names": list(names), "bone_lengths": bones}


def direction_guide(model: AAMDMMotion, delta: Tensor, scale: float) -> Guide:
    """Eq. 13's cost for a commanded direction ``delta`` (B,), radians, in the heading frame.

    :math:`J = \\sum_h \\|(\\cos, \\sin)_h(\\hat x) - (\\cos\\delta, \\sin\\delta)\\|^2` over the
    facing directions of every horizon in :math:`\\hat x` (the engineered features of the clean
    estimate).
    """
    n_h = len(model.config.horizons)
    target = torch.stack([torch.cos(delta), torch.sin(delta)], -1)  # (B, 2)

    def cost(xz0: Tensor) -> Tensor:
        dirs = model.x_of(xz0)[:, 2 * n_h :].unflatten(-1, (n_h, 2))  # (B, H, 2)
        return ((dirs - target[:, None]) ** 2).sum((-1, -2))

    return Guide(cost, scale)


@torch.no_grad()
def aamdm_frame(
    model: AAMDMMotion,
    frame: Tensor,
    generator: torch.Generator | NoiseTape | None = None,
    guide: Guide | None = None,
    T_adm: int | None = None,
) -> Tensor:
    """One auto-regressive step of the motion AAMDM: ``[xz, y]`` (B, XZ + D) of the next frame.

    The transition samples the next standardised latent ``xz`` from the previous one (the first
    XZ columns of ``frame``; generation + polishing, :func:`~minimdm.aamdm.model.aamdm_sample`),
    then the decoder gives its pose features ``y`` (A-MDM units). ``generator`` may be a
    :class:`~minimdm.diffusion.NoiseTape` (the fast path, :mod:`minimdm.fast`).
    """
    xz = model.transition.sample(
        frame[:, : model.xz_dim].contiguous(), generator, guide=guide, T_adm=T_adm
    )  # (B, XZ)
    return torch.cat([xz, model.decode(xz)], dim=1)  # (B, XZ + D)


def _check_rollout(
    model: AAMDMMotion,
    init_y: Tensor,
    init_x: Tensor,
    n_frames: int,
    fast: Callable | None,
    eager_only: bool,
) -> None:
    """Refuse initial frames, frame counts or a fast step that :func:`rollout_aamdm` cannot use;
    ``eager_only``: guidance or ``T_adm`` was asked for."""
    if fast is not None and eager_only:
        raise ValueError("guidance and T_adm need the eager step: pass fast=None with them")
    if fast is not None:  # a graph exported from another model is refused
        check_same_model("fast", fast, model, "aamdm_motion", "the AAMDM model given")
    if init_y.dim() != 2 or init_x.dim() != 2 or init_y.shape[0] != init_x.shape[0]:
        raise ValueError(
            f"init_y and init_x must be (C, D) and (C, {model.config.x_dim}), got "
            f"{tuple(init_y.shape)} and {tuple(init_x.shape)}"
        )
    if init_x.shape[1] != model.config.x_dim or init_y.shape[1] != model.config.y_dim:
        raise ValueError(
            f"init_y and init_x must have {model.config.y_dim} and {model.config.x_dim} "
            f"columns, got {init_y.shape[1]} and {init_x.shape[1]}"
        )
    for name, t in (("init_y", init_y), ("init_x", init_x)):
        if not torch.isfinite(t).all():
            raise ValueError(f"{name} must be finite, but it holds NaN/Inf")
    if not isinstance(n_frames, int) or n_frames < 1:
        raise ValueError(f"n_frames must be an integer >= 1, got {n_frames!r}")


@torch.no_grad()
def rollout_aamdm(
    model: AAMDMMotion,
    init_y: Tensor,
    init_x: Tensor,
    n_frames: int,
    n_samples: int = 1,
    generator: torch.Generator | None = None,
    *,
    start_pose: StartPose | None = None,
    T_adm: int | None = None,
    direction: Tensor | float | None = None,
    guide_scale: float = 0.0,
    decode_positions: bool = True,
    fast: Callable[[Tensor, torch.Generator | None], Tensor] | None = None,
) -> Rollout:
    """Sample ``n_samples`` futures of ``n_frames`` from each initial frame (C, D), (C, 12).

    ``T_adm = 0`` skips polishing (the GAN's draft is the frame). ``direction`` (C,) or a
    number: the commanded world heading in radians; with ``guide_scale`` > 0 each frame is
    guided towards it (eq. 13; the command is converted to the current heading frame).
    ``Rollout.normalized`` holds the standardised xz. ``fast(frame, generator) -> frame``
    replaces :func:`aamdm_frame` as the per-frame step, e.g. a
    :class:`minimdm.fast.FastFrame` of the same model (the same chain as one graph); guidance
    needs the eager step.
    """
    _check_rollout(model, init_y, init_x, n_frames, fast, guide_scale > 0 or T_adm is not None)
    dev = model.y_mean.device
    C, K = init_y.shape[0], n_samples
    if start_pose is None:
        start_pose = StartPose(torch.zeros(C, 2), torch.zeros(C))
    xy0 = torch.as_tensor(start_pose.xy, dtype=torch.float32).reshape(C, 2)
    h0 = torch.as_tensor(start_pose.heading, dtype=torch.float32).reshape(C)
    heading = h0.repeat_interleave(K).to(dev)  # (C K,)
    if direction is not None:
        direction = torch.as_tensor(direction, dtype=torch.float32, device=dev).expand(C)
        direction = direction.repeat_interleave(K)
    y0 = init_y.to(dev).repeat_interleave(K, dim=0)  # (C K, D)
    xz0 = model.encode(init_y.to(dev), init_x.to(dev)).repeat_interleave(K, dim=0)  # (C K, XZ)
    XZ = xz0.shape[1]

    def step(f: int, frame: Tensor) -> Tensor:
        """Frame f as [xz, y] (C K, XZ + D): sample the latent, then decode the pose."""
        nonlocal heading
        if fast is not None:
            frame = fast(frame, generator)
        else:
            guide = None
            if direction is not None and guide_scale > 0:
                guide = direction_guide(model, wrap_angle(direction - heading), guide_scale)
            frame = aamdm_frame(model, frame, generator, guide=guide, T_adm=T_adm)
        heading = heading + frame[:, XZ + 2]  # the yaw rate d_r
        return frame

    def who(b: int) -> str:
        """Names batch row ``b`` in an error."""
        return f"character {b // K}, sample {b % K}"

    frames = autoregress(step, torch.cat([xz0, y0], dim=1), n_frames, who=who)  # (C K, F, XZ + D)
    features = frames[..., XZ:].reshape(C, K, n_frames, -1)
    normalized = frames[..., :XZ].reshape(C, K, n_frames, -1)
    positions = None
    if decode_positions:
        sp = StartPose(xy0[:, None].expand(C, K, 2).double(), h0[:, None].expand(C, K).double())
        positions = decode(features.double(), sp).float()  # (C, K, F, J, 3)
    return Rollout(features=features, positions=positions, normalized=normalized)


# --------------------------------------------------------------------------------------------
# Metrics


def local_poses(features: Tensor, n_joints: int) -> Tensor:
    """Root-relative joint positions in the heading frame, in cm: ``(..., D) -> (N, 3 J)``."""
    return features[..., 3 : 3 + 3 * n_joints].reshape(-1, 3 * n_joints) * metrics.CM


def pose_diversity(poses: Tensor, n_pairs: int = 2000, seed: int = 0) -> float:
    """MDM's Diversity: the mean distance between ``n_pairs`` random pairs of poses (N, P)."""
    g = torch.Generator().manual_seed(seed)
    i = torch.randint(0, poses.shape[0], (n_pairs,), generator=g)
    j = torch.randint(0, poses.shape[0], (n_pairs,), generator=g)
    return float((poses[i].double() - poses[j].double()).norm(dim=-1).mean())


def pose_frechet_distance(a: Tensor, b: Tensor) -> float:
    """Fréchet distance between Gaussian fits of two pose sets (N, P), (M, P).

    :math:`\\|\\mu_a - \\mu_b\\|^2 +
    \\mathrm{tr}(\\Sigma_a + \\Sigma_b - 2(\\Sigma_a\\Sigma_b)^{1/2})`
    """
    a, b = a.double(), b.double()
    mu_a, mu_b = a.mean(0), b.mean(0)
    ca, cb = torch.cov(a.T), torch.cov(b.T)
    # tr sqrt(ca cb) from the eigenvalues of sqrt(ca) cb sqrt(ca), which is symmetric
    w, v = torch.linalg.eigh(ca)
    sa = v @ torch.diag(w.clamp(min=0).sqrt()) @ v.T
    ev = torch.linalg.eigvalsh(sa @ cb @ sa).clamp(min=0)
    return float((mu_a - mu_b).pow(2).sum() + ca.trace() + cb.trace() - 2 * ev.sqrt().sum())


def motion_quality(
    rollout: Rollout,
    skeleton: Any,
    data_poses: Tensor,
    foot_offset: list[float] | float = 0.0,
    bone_lengths: Tensor | None = None,
) -> dict[str, float]:
    """The comparison's quality columns for one rollout (C characters, K >= 2 samples each).

    ``APD`` (cm, mean over characters), ``FS`` (cm/frame), ``Bone.Err`` (cm), ``Jnt.Accel``
    (cm/frame²) from :mod:`minimdm.motion.metrics`; ``DIV`` and ``FD`` against ``data_poses``
    (:func:`local_poses` of the dataset). Bone.Err is measured against each character's
    ``bone_lengths`` (C, J - 1) when given (a corpus of several actors), else the skeleton's.
    """
    pos = rollout.positions  # (C, K, F, J, 3)
    ref = metrics.skeleton_bone_lengths(skeleton.offsets, skeleton.parents)
    feet = skeleton.foot_indices
    m = metrics.motion_metrics(pos, skeleton.parents, feet, ref, foot_offset=foot_offset)
    if bone_lengths is not None:  # each character against its own bones
        errors = [
            metrics.bone_length_error(pos[c], skeleton.parents, bone_lengths[c])
            for c in range(pos.shape[0])
        ]
        m["Bone.Err"] = float(np.mean(errors))
    poses = local_poses(rollout.features, pos.shape[-2])
    return {
        **{k: m[k] for k in ("APD", "FS", "Bone.Err", "Jnt.Accel")},
        "DIV": pose_diversity(poses),
        "FD": pose_frechet_distance(poses, data_poses),
    }


def heading_tracking_error(rollout: Rollout, start: StartPose, direction: Tensor, settle: int = 30):
    """Mean absolute angle (degrees) between the root heading and the command after ``settle``."""
    feats = rollout.features  # (C, K, F, D)
    C, K = feats.shape[:2]
    h0 = torch.as_tensor(start.heading, dtype=torch.float32).reshape(C, 1, 1)
    heading = h0 + torch.cumsum(feats[..., 2], dim=-1)  # (C, K, F)
    cmd = torch.as_tensor(direction, dtype=torch.float32).expand(C).reshape(C, 1, 1)
    err = wrap_angle(heading - cmd)[..., settle:].abs()
    return float(err.mean() * 180 / math.pi)
