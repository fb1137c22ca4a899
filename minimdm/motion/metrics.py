"""Motion metrics of A-MDM §7.3 (Shi et al. 2024), on global joint positions.

Every function takes joint positions in **metres, z-up**, shaped ``(F, J, 3)`` for one motion or
``(K, F, J, 3)`` for ``K`` samples (numpy arrays or torch tensors), and returns plain floats in
**centimetres** (or cm per frame, cm per frame², percent, as documented). The evaluation protocol
of the paper (Table 1): 50 samples from fixed initial states; APD over 150 frames; ADE and FDE
over 60 frames against the ground-truth continuation that starts from the same initial state;
mean ± std over repeated seeds (:func:`mean_std`, :func:`over_seeds`).

Distances between two motions follow the authors' evaluation code: the *mean per-joint position
distance*, i.e. the Euclidean distance of each joint averaged over joints and frames,

.. math:: d(x, y) = \\frac{1}{F J} \\sum_{f, j} \\| x_{f,j} - y_{f,j} \\|_2 .

Foot contact. The foot joints of a skeleton (ankles for the DeepMimic humanoid) sit above the
floor even when the foot is flat on it. Every foot metric therefore measures the *height above
contact* :math:`h = z - z_0`, where :math:`z_0` (``foot_offset``) is the height of the foot joint
when its foot rests on the floor. :func:`foot_contact_offsets` estimates it from ground-truth
data as a low quantile of each foot joint's height.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np
import torch
from torch import Tensor

from .skeleton import bone_pairs

__all__ = [
    "CM",
    "apd",
    "ade_fde",
    "bone_lengths",
    "skeleton_bone_lengths",
    "bone_length_error",
    "joint_acceleration",
    "foot_sliding",
    "contact_weight",
    "foot_penetration",
    "foot_contact_offsets",
    "motion_metrics",
    "mean_std",
    "over_seeds",
]

CM = 100.0
"""Centimetres per metre: every metric is reported in cm."""

ArrayLike = Tensor | np.ndarray


def _positions(name: str, x: ArrayLike, batched: bool | None = None) -> Tensor:
    """Convert to a float64 tensor and check the shape ``(..., F, J, 3)`` and finiteness."""
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, Tensor) else x).detach()
    t = t.to(device="cpu", dtype=torch.float64)
    if t.dim() not in (3, 4) or t.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (F, J, 3) or (K, F, J, 3), got {tuple(t.shape)}")
    if batched is True and t.dim() != 4:
        raise ValueError(f"{name} must have shape (K, F, J, 3), got {tuple(t.shape)}")
    if batched is False and t.dim() != 3:
        raise ValueError(f"{name} must have shape (F, J, 3), got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite, but it holds NaN/Inf")
    return t


def _mean_joint_distance(a: Tensor, b: Tensor) -> Tensor:
    """Per-frame mean over joints of the Euclidean distance: ``(..., F, J, 3) -> (..., F)``."""
    return (a - b).norm(dim=-1).mean(dim=-1)


def apd(samples: ArrayLike) -> float:
    """Average Pairwise Distance (A-MDM eq. 9), in cm. Higher means more diverse.

    .. math:: \\mathrm{APD} = \\frac{1}{K(K-1)} \\sum_{i=1}^K \\sum_{j \\ne i} d(x_i, x_j)

    with :math:`d` the mean per-joint position distance (module docstring).

    Args:
        samples: ``(K, F, J, 3)``, K >= 2 motions from the same initial state.
    """
    x = _positions("samples", samples, batched=True)
    K = x.shape[0]
    if K < 2:
        raise ValueError(f"samples must hold K >= 2 motions for APD, got K={K}")
    d = _mean_joint_distance(x[:, None], x[None]).mean(-1)  # (K, K)
    return float(d.sum() / (K * (K - 1)) * CM)


def ade_fde(samples: ArrayLike, reference: ArrayLike) -> tuple[float, float]:
    """Average and Final Displacement Errors (A-MDM eq. 10 and §7.3), in cm. Lower is better.

    .. math:: \\mathrm{ADE} = \\min_{i} \\frac{1}{F}\\sum_f \\frac{1}{J}\\sum_j
              \\|x_{i,f,j} - x^{ref}_{f,j}\\|,
              \\qquad \\mathrm{FDE} = \\min_i \\frac{1}{J}\\sum_j \\|x_{i,F,j} - x^{ref}_{F,j}\\|

    Each is the best over the K samples (the closest sample to the ground truth), taken
    independently for ADE and FDE.

    Args:
        samples: ``(K, F, J, 3)`` generated motions (the paper uses F = 60).
        reference: ``(F, J, 3)`` the ground-truth continuation from the same initial state.
    """
    x = _positions("samples", samples, batched=True)
    ref = _positions("reference", reference, batched=False)
    if x.shape[1:] != ref.shape:
        raise ValueError(
            f"reference must have shape {tuple(x.shape[1:])} to match samples, "
            f"got {tuple(ref.shape)}"
        )
    per_frame = _mean_joint_distance(x, ref[None])  # (K, F)
    return float(per_frame.mean(-1).min() * CM), float(per_frame[:, -1].min() * CM)


def bone_lengths(positions: ArrayLike, parents: Sequence[int]) -> Tensor:
    """Length in metres of every bone (joint to its parent): ``(..., F, J, 3) -> (..., F, B)``.

    The bones are the joints with a parent (``parents[j] >= 0``), in joint order.
    """
    x = _positions("positions", positions)
    if len(parents) != x.shape[-2]:
        raise ValueError(
            f"parents must have {x.shape[-2]} entries (one per joint), got {len(parents)}"
        )
    child, par = bone_pairs(parents)
    return (x[..., child, :] - x[..., par, :]).norm(dim=-1)


def skeleton_bone_lengths(offsets: ArrayLike, parents: Sequence[int]) -> Tensor:
    """Rest bone lengths in metres from a skeleton's ``(J, 3)`` offsets: ``(B,)``.

    The offset of joint j is its position relative to its parent, so the bone length is its norm.
    """
    o = torch.as_tensor(np.asarray(offsets), dtype=torch.float64)
    if o.shape != (len(parents), 3):
        raise ValueError(f"offsets must have shape ({len(parents)}, 3), got {tuple(o.shape)}")
    return o[bone_pairs(parents)[0]].norm(dim=-1)


def bone_length_error(
    positions: ArrayLike, parents: Sequence[int], reference_lengths: ArrayLike
) -> float:
    """Bone length error (A-MDM eq. 11), in cm: the mean deviation from rigid bones.

    .. math:: \\mathrm{Bone\\_Err} = \\frac{1}{B}\\sum_{b} |\\hat L_b - L_b|

    averaged over frames (and samples). :math:`\\hat L_b` is measured from the joint positions,
    :math:`L_b` the ground-truth length (:func:`skeleton_bone_lengths`, or :func:`bone_lengths`
    of the data averaged over frames).

    Args:
        positions: ``(F, J, 3)`` or ``(K, F, J, 3)``.
        parents: the skeleton's parent indices (-1 for the root).
        reference_lengths: ``(B,)`` bone lengths in metres, one per joint with a parent.
    """
    L_hat = bone_lengths(positions, parents)  # (..., F, B)
    L = torch.as_tensor(np.asarray(reference_lengths), dtype=torch.float64).flatten()
    if L.shape[0] != L_hat.shape[-1]:
        raise ValueError(
            f"reference_lengths must have {L_hat.shape[-1]} entries (one per bone), "
            f"got {L.shape[0]}"
        )
    return float((L_hat - L).abs().mean() * CM)


def joint_acceleration(positions: ArrayLike, fps: float | None = None) -> float:
    """Mean joint acceleration (Jnt.Accel), the norm of second differences; the paper's jitter.

    .. math:: \\mathrm{Accel} = \\frac{1}{(F-2) J}\\sum_{f,j} \\|x_{f+1,j} - 2x_{f,j} + x_{f-1,j}\\|

    In **cm / frame²** by default, so it depends on the frame rate (the paper's data are 30 Hz);
    with ``fps`` given it is multiplied by ``fps²`` and reported in cm / s². The target is the
    dataset's own value (Table 1 reports it as a row): lower is not better, closer is.
    """
    x = _positions("positions", positions)
    if x.shape[-3] < 3:
        raise ValueError(f"positions need at least 3 frames for an acceleration, got {x.shape[-3]}")
    a = x[..., 2:, :, :] - 2 * x[..., 1:-1, :, :] + x[..., :-2, :, :]  # (..., F-2, J, 3)
    scale = 1.0 if fps is None else float(fps) ** 2
    return float(a.norm(dim=-1).mean() * CM * scale)


def _foot_heights(x: Tensor, foot_joints: Sequence[int], foot_offset) -> Tensor:
    """Height above contact ``h = z - z_0`` of each foot joint: ``(..., F, n_feet)``."""
    if len(foot_joints) == 0:
        raise ValueError("foot_joints must name at least one joint")
    J = x.shape[-2]
    if any(not 0 <= j < J for j in foot_joints):
        raise ValueError(f"foot_joints must lie in [0, {J}), got {list(foot_joints)}")
    z0 = torch.as_tensor(np.asarray(foot_offset), dtype=torch.float64).flatten()
    if z0.numel() not in (1, len(foot_joints)):
        raise ValueError(
            f"foot_offset must be a number or hold {len(foot_joints)} values, got {z0.numel()}"
        )
    return x[..., list(foot_joints), 2] - z0


def foot_sliding(
    positions: ArrayLike,
    foot_joints: Sequence[int],
    height_threshold: float = 0.025,
    foot_offset: float | Sequence[float] = 0.0,
) -> float:
    """Foot sliding (FS), after Ling et al. (2020) and Zhang et al. (2018), in cm / frame.

    Horizontal foot displacement, weighted by how close the foot is to the ground:

    .. math:: \\mathrm{FS} = \\frac{1}{(F-1) N}\\sum_{f, n} \\|\\Delta p^{xy}_{f,n}\\|
              \\left(2 - 2^{\\,\\mathrm{clip}(h_{f,n}/H,\\,0,\\,1)}\\right)

    where :math:`\\Delta p^{xy}_{f,n}` is the horizontal displacement of foot joint n between
    frames f and f+1, :math:`h_{f,n}` its height above contact in frame f+1 and :math:`H` the
    height threshold (default 2.5 cm). A foot on the ground (h <= 0) counts fully, a foot at
    H or above not at all. Averaged over all foot-frames, airborne ones included.

    Args:
        positions: ``(F, J, 3)`` or ``(K, F, J, 3)`` in metres, z-up.
        foot_joints: indices of the foot joints (e.g. ``Skeleton.foot_joints``).
        height_threshold: H in metres.
        foot_offset: foot joint height when the foot is flat on the floor (one value or one per
            foot joint); see :func:`foot_contact_offsets`.
    """
    x = _positions("positions", positions)
    if height_threshold <= 0:
        raise ValueError(f"height_threshold must be > 0, got {height_threshold}")
    if x.shape[-3] < 2:
        raise ValueError(f"positions need at least 2 frames for foot sliding, got {x.shape[-3]}")
    h = _foot_heights(x, foot_joints, foot_offset)[..., 1:, :]  # (..., F-1, N)
    feet = x[..., list(foot_joints), :]  # (..., F, N, 3)
    disp = (feet[..., 1:, :, :2] - feet[..., :-1, :, :2]).norm(dim=-1)  # (..., F-1, N)
    return float((disp * contact_weight(h, height_threshold)).mean() * CM)


def contact_weight(height: Tensor, height_threshold: float = 0.025) -> Tensor:
    """How much a foot counts as on the ground in :func:`foot_sliding`: :math:`2 -
    2^{\\mathrm{clip}(h/H, 0, 1)}`, 1 at or below contact height, 0 from ``height_threshold`` up."""
    return 2 - 2 ** (height / height_threshold).clamp(0, 1)


def foot_penetration(
    positions: ArrayLike,
    foot_joints: Sequence[int],
    tolerance: float = 0.01,
    foot_offset: float | Sequence[float] = 0.0,
) -> tuple[float, float]:
    """Foot penetration frequency (%) and distance (cm), after Rempe et al. (2021).

    A foot-frame penetrates when its height above contact is below ``-tolerance``
    (default 1 cm below the floor):

    .. math:: \\mathrm{Pen.Freq} = 100\\,\\frac{|\\{(f,n): h_{f,n} < -\\tau\\}|}{F N},\\qquad
              \\mathrm{Pen.Dist} = \\mathrm{mean}_{(f,n): h_{f,n} < -\\tau} (-h_{f,n})

    Pen.Dist is the mean depth over the penetrating foot-frames (0 when there are none).

    Returns:
        ``(frequency_percent, distance_cm)``.
    """
    x = _positions("positions", positions)
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    h = _foot_heights(x, foot_joints, foot_offset)  # (..., F, N)
    pen = h < -tolerance
    freq = float(pen.double().mean() * 100.0)
    dist = float((-h[pen]).mean() * CM) if pen.any() else 0.0
    return freq, dist


def foot_contact_offsets(
    positions: ArrayLike, foot_joints: Sequence[int], quantile: float = 0.05
) -> list[float]:
    """Estimate each foot joint's height on contact from ground-truth motion, in metres.

    Returns the ``quantile`` of each foot joint's height over all frames: the level at which the
    foot rests on the floor, robust to a few frames of noise.
    """
    x = _positions("positions", positions)
    if not 0 <= quantile <= 1:
        raise ValueError(f"quantile must lie in [0, 1], got {quantile}")
    z = x[..., list(foot_joints), 2].reshape(-1, len(foot_joints))  # (frames, N)
    return torch.quantile(z, quantile, dim=0).tolist()


def motion_metrics(
    samples: ArrayLike,
    parents: Sequence[int],
    foot_joints: Sequence[int],
    reference_lengths: ArrayLike,
    reference: ArrayLike | None = None,
    ade_frames: int = 60,
    foot_offset: float | Sequence[float] = 0.0,
    height_threshold: float = 0.025,
    tolerance: float = 0.01,
) -> dict[str, float]:
    """The Table 1 row for ``K`` samples from one initial state.

    Args:
        samples: ``(K, F, J, 3)`` generated motions (the paper: K = 50, F = 150);
            ``(C, K, F, J, 3)`` for C initial states (APD is the mean of their APDs, the
            other metrics pool all motions; no ADE/FDE); or one motion ``(F, J, 3)`` (no APD,
            e.g. a clip of the dataset).
        parents, foot_joints: the skeleton.
        reference_lengths: ``(B,)`` ground-truth bone lengths in metres.
        reference: ``(F_ref, J, 3)`` ground-truth continuation; ADE/FDE use its first
            ``ade_frames`` frames and those of the samples. Omitted: no ADE/FDE.

    Returns:
        ``{"APD", "ADE", "FDE", "FS", "Bone.Err", "Jnt.Accel", "Pen.Freq", "Pen.Dist"}``
        in cm (cm / frame for FS, cm / frame² for Jnt.Accel, % for Pen.Freq).
    """
    t = torch.as_tensor(np.asarray(samples) if not isinstance(samples, Tensor) else samples)
    if t.dim() == 5:
        if reference is not None:
            raise ValueError("reference needs samples from one initial state, (K, F, J, 3)")
        x = _positions("samples", t.flatten(0, 1), batched=True)
        out = {"APD": sum(apd(x_c) for x_c in x.unflatten(0, t.shape[:2])) / t.shape[0]}
    elif t.dim() == 3:
        x, out = _positions("samples", t, batched=False), {}
    else:
        x = _positions("samples", t, batched=True)
        out = {"APD": apd(x)}
    if reference is not None:
        ref = _positions("reference", reference, batched=False)
        xk = x if x.dim() == 4 else x[None]  # (K, F, J, 3)
        n = min(ade_frames, ref.shape[0], xk.shape[1])
        out["ADE"], out["FDE"] = ade_fde(xk[:, :n], ref[:n])
    out["FS"] = foot_sliding(x, foot_joints, height_threshold, foot_offset)
    out["Bone.Err"] = bone_length_error(x, parents, reference_lengths)
    out["Jnt.Accel"] = joint_acceleration(x)
    out["Pen.Freq"], out["Pen.Dist"] = foot_penetration(x, foot_joints, tolerance, foot_offset)
    return out


def mean_std(values: Iterable[float]) -> tuple[float, float]:
    """Mean and (population) standard deviation of repeated measurements."""
    v = np.asarray(list(values), dtype=np.float64)
    if v.size == 0:
        raise ValueError("values must hold at least one measurement")
    return float(v.mean()), float(v.std())


def over_seeds(
    fn: Callable[[int], dict[str, float]], seeds: Iterable[int]
) -> dict[str, tuple[float, float]]:
    """Run ``fn(seed) -> {metric: value}`` for every seed; return ``{metric: (mean, std)}``.

    This is the paper's "mean ± std over repeated runs".
    """
    runs = [fn(int(s)) for s in seeds]
    if not runs:
        raise ValueError("seeds must hold at least one seed")
    keys = runs[0].keys()
    return {k: mean_std(r[k] for r in runs) for k in keys}
