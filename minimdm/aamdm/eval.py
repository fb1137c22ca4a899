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
:func:`frames_per_second` times one character (batch 1), the interactive setting.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from minimdm.aamdm.model import Guide
from minimdm.aamdm.motion import AAMDMMotion
from minimdm.amdm.sampling import NonFiniteFrameError, Rollout
from minimdm.motion import metrics
from minimdm.motion.features import StartPose, decode, start_pose_of
from minimdm.motion.skeleton import wrap_angle

__all__ = [
    "INITIAL_CLIPS",
    "initial_states",
    "direction_guide",
    "rollout_aamdm",
    "local_poses",
    "pose_diversity",
    "pose_frechet_distance",
    "motion_quality",
    "heading_tracking_error",
    "frames_per_second",
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
    data: dict, names: tuple[str, ...] = INITIAL_CLIPS, row: int = 10
) -> dict[str, Any]:
    """Initial frames from :func:`~minimdm.aamdm.load_motion_data`'s ``data``.

    Returns ``y`` (C, D) and ``x`` (C, 12) of feature row ``row`` of each named clip, and the
    ``start`` pose (root ground position and heading at that frame) that decoding starts from.
    """
    clips = data["clips"]
    idx = [clips.names.index(n) for n in names]
    y = torch.stack([data["y"][i][row] for i in idx])
    x = torch.stack([data["x"][i][row] for i in idx])
    starts = [start_pose_of(clips[i], row + 1) for i in idx]  # row r is clip frame r + 1
    start = StartPose(
        torch.stack([s.xy for s in starts]),
        torch.stack([torch.as_tensor(s.heading) for s in starts]),
    )
    return {"y": y, "x": x, "start": start, "names": list(names)}


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
) -> Rollout:
    """Sample ``n_samples`` futures of ``n_frames`` from each initial frame (C, D), (C, 12).

    ``T_adm = 0`` skips polishing (the GAN's draft is the frame). ``direction`` (C,) or a
    number: the commanded world heading in radians; with ``guide_scale`` > 0 each frame is
    guided towards it (eq. 13; the command is converted to the current heading frame).
    ``Rollout.normalized`` holds the standardised xz.
    """
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
    xz = model.encode(init_y.to(dev), init_x.to(dev)).repeat_interleave(K, dim=0)  # (C K, XZ)
    feats, lat = [], []
    for f in range(n_frames):
        guide = None
        if direction is not None and guide_scale > 0:
            guide = direction_guide(model, wrap_angle(direction - heading), guide_scale)
        xz = model.transition.sample(xz, generator, guide=guide, T_adm=T_adm)
        y = model.decode(xz)  # (C K, D)
        ok = torch.isfinite(y).all(1) & torch.isfinite(xz).all(1)
        if not ok.all():
            b = int((~ok).nonzero()[0])
            raise NonFiniteFrameError(
                f"rollout produced a non-finite frame {f + 1} (of {n_frames}) for character "
                f"{b // K}, sample {b % K}"
            )
        heading = heading + y[:, 2]  # the yaw rate d_r
        feats.append(y.float().cpu())
        lat.append(xz.float().cpu())
    features = torch.stack(feats, 1).reshape(C, K, n_frames, -1)
    normalized = torch.stack(lat, 1).reshape(C, K, n_frames, -1)
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
) -> dict[str, float]:
    """The comparison's quality columns for one rollout (C characters, K >= 2 samples each).

    ``APD`` (cm, mean over characters), ``FS`` (cm/frame), ``Bone.Err`` (cm), ``Jnt.Accel``
    (cm/frame²) from :mod:`minimdm.motion.metrics`; ``DIV`` and ``FD`` against ``data_poses``
    (:func:`local_poses` of the dataset).
    """
    pos = rollout.positions  # (C, K, F, J, 3)
    C, K, F, J, _ = pos.shape
    ref = metrics.skeleton_bone_lengths(skeleton.offsets, skeleton.parents)
    flat = pos.reshape(C * K, F, J, 3)
    poses = local_poses(rollout.features, J)
    return {
        "APD": sum(metrics.apd(pos[c]) for c in range(C)) / C,
        "FS": metrics.foot_sliding(flat, skeleton.foot_indices, foot_offset=foot_offset),
        "Bone.Err": metrics.bone_length_error(flat, skeleton.parents, ref),
        "Jnt.Accel": metrics.joint_acceleration(flat),
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


def frames_per_second(step: Callable[[], Any], n_frames: int = 60, warmup: int = 5) -> float:
    """Frames per second of ``step()``, which makes one frame (batch 1), best of two passes."""
    for _ in range(warmup):
        step()
    best = float("inf")
    for _ in range(2):
        t0 = time.perf_counter()
        for _ in range(n_frames):
            step()
        best = min(best, time.perf_counter() - t0)
    return n_frames / best


# --------------------------------------------------------------------------------------------
# The comparison of AAMDM §4.1 on our data


def _amdm_stepper(ckpt: Any, steps: int | None, eta: float, device: torch.device):
    """``(next_frame(cond, generator) -> frame, normalize)`` for an A-MDM checkpoint."""
    from minimdm.amdm.sampling import next_frame
    from minimdm.motion.features import Normalizer

    d = ckpt.metadata.get("diffusion") or {}
    sched = ckpt.schedule(device)
    norm = Normalizer.from_dict(ckpt.normalizer)
    model = ckpt.model.to(device).eval()

    def step(cond: Tensor, g: torch.Generator | None) -> Tensor:
        return next_frame(
            model, cond, g, sched, steps, eta, d.get("predicts", "eps"), d.get("clip_x0")
        )

    return step, norm


def motion_comparison(
    amdm: Any,
    aamdm: AAMDMMotion,
    data: dict,
    n_frames: int = 120,
    n_samples: int = 8,
    amdm_steps: tuple[int | None, ...] = (5, None),
    eta: float = 1.0,
    seed: int = 0,
    fps_frames: int = 60,
    device: str = "cpu",
    names: tuple[str, ...] = INITIAL_CLIPS,
    include_unpolished: bool = True,
) -> tuple[list[dict], dict[str, Rollout]]:
    """A-MDM at 5 (DDIM) and at all T steps vs AAMDM (3 + 2), in one run (AAMDM Table 1).

    Every method rolls out ``n_samples`` futures of ``n_frames`` from the same initial frames
    (:func:`initial_states` of ``names``) with the same seed, then :func:`motion_quality` scores
    them and :func:`frames_per_second` times one character (network calls plus decoding a
    pose; the CPU runs one thread for batch 1). ``amdm`` is a loaded A-MDM
    :class:`~minimdm.checkpoint.Checkpoint`. Returns the rows and the rollouts by method name.
    """
    from minimdm.amdm.sampling import rollout

    dev = torch.device(device)
    sk = data["skeleton"]
    init = initial_states(data, names)
    data_poses = local_poses(torch.cat(data["y"]), len(sk))
    all_pos = torch.cat([torch.as_tensor(c.positions) for c in data["clips"]])
    foot = metrics.foot_contact_offsets(all_pos, sk.foot_indices)
    T = int((amdm.metadata.get("diffusion") or {}).get("T", 0))
    aamdm = aamdm.to(dev).eval()
    rows, rolls = [], {}
    methods: list[tuple[str, Any]] = [(f"amdm{s or T}", s) for s in amdm_steps]
    methods += [("aamdm", None)] + ([("aamdm_3+0", 0)] if include_unpolished else [])
    for name, arg in methods:
        g = torch.Generator(dev).manual_seed(seed)
        t0 = time.perf_counter()
        if name.startswith("amdm"):
            r = rollout(
                amdm, init["y"], n_frames, n_samples, arg, g, start_pose=init["start"], eta=eta,
                device=dev,
            )  # fmt: skip
            step_fn, norm = _amdm_stepper(amdm, arg, eta, dev)
            state = {"x": norm.normalize(init["y"][:1]).to(dev)}
            calls = arg or T

            def one(state=state, step_fn=step_fn):
                state["x"] = step_fn(state["x"], None)

        else:
            r = rollout_aamdm(
                aamdm, init["y"], init["x"], n_frames, n_samples, g, start_pose=init["start"],
                T_adm=arg,
            )  # fmt: skip
            state = {"x": aamdm.encode(init["y"][:1].to(dev), init["x"][:1].to(dev))}
            calls = aamdm.transition.T_gan + (aamdm.transition.T_adm if arg is None else arg)

            def one(state=state, arg=arg):
                with torch.no_grad():
                    state["x"] = aamdm.transition.sample(state["x"], None, T_adm=arg)
                    aamdm.decode(state["x"])

        seconds = time.perf_counter() - t0
        with _one_thread(dev):
            fps = frames_per_second(one, fps_frames)
        row = {"method": name, "network_calls": calls, **motion_quality(r, sk, data_poses, foot)}
        row.update(fps=fps, rollout_s=seconds)
        rows.append({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()})
        rolls[name] = r
    return rows, rolls


class _one_thread:
    def __init__(self, dev: torch.device) -> None:
        self.on = dev.type == "cpu"

    def __enter__(self):
        self.old = torch.get_num_threads()
        if self.on:
            torch.set_num_threads(1)

    def __exit__(self, *exc):
        torch.set_num_threads(self.old)


def dataset_quality(data: dict) -> dict[str, float]:
    """The data's own DIV and the metrics of its clips (the target row of the table)."""
    sk = data["skeleton"]
    poses = local_poses(torch.cat(data["y"]), len(sk))
    pos = [torch.as_tensor(c.positions, dtype=torch.float64) for c in data["clips"]]
    all_pos = torch.cat(pos)
    foot = metrics.foot_contact_offsets(all_pos, sk.foot_indices)
    ref = metrics.skeleton_bone_lengths(sk.offsets, sk.parents)
    n = sum(len(p) for p in pos)
    w = [len(p) / n for p in pos]
    return {
        "FS": sum(
            wi * metrics.foot_sliding(p, sk.foot_indices, foot_offset=foot)
            for wi, p in zip(w, pos, strict=True)
        ),
        "Bone.Err": metrics.bone_length_error(all_pos, sk.parents, ref),
        "Jnt.Accel": sum(wi * metrics.joint_acceleration(p) for wi, p in zip(w, pos, strict=True)),
        "DIV": pose_diversity(poses),
    }


def guidance_study(
    model: AAMDMMotion,
    data: dict,
    turns_deg: tuple[float, ...] = (90.0, -90.0, 180.0),
    scales: tuple[float, ...] = (0.0, 0.5, 2.0),
    names: tuple[str, ...] = ("walk", "run"),
    n_frames: int = 150,
    n_samples: int = 4,
    settle: int = 45,
    seed: int = 0,
    device: str = "cpu",
) -> list[dict]:
    """Root-direction control (AAMDM §3.5, eq. 13): heading tracking error per guidance scale.

    From each initial frame of ``names``, the command is the start heading turned by each of
    ``turns_deg``; ``TE`` is the mean absolute heading error in degrees after ``settle`` frames
    (AAMDM's TE-UC on the realised root heading), ``TE_x`` the error of the facing directions
    in the generated :math:`\\hat x` (the paper's :math:`|\\bar x - \\hat x|`, in degrees), and
    ``fps`` the speed for one character. Scale 0 is the unguided model.
    """
    dev = torch.device(device)
    model = model.to(dev).eval()
    init = initial_states(data, names)
    sk = data["skeleton"]
    data_poses = local_poses(torch.cat(data["y"]), len(sk))
    rows = []
    for scale in scales:
        te, te_x, fd = [], [], []
        for turn in turns_deg:
            cmd = init["start"].heading.float() + math.radians(turn)  # (C,)
            g = torch.Generator(dev).manual_seed(seed)
            r = rollout_aamdm(
                model, init["y"], init["x"], n_frames, n_samples, g, start_pose=init["start"],
                direction=cmd, guide_scale=scale,
            )  # fmt: skip
            te.append(heading_tracking_error(r, init["start"], cmd, settle))
            te_x.append(_x_direction_error(model, r, init["start"], cmd, settle))
            fd.append(pose_frechet_distance(local_poses(r.features, len(sk)), data_poses))
        state = {"x": model.encode(init["y"][:1].to(dev), init["x"][:1].to(dev))}
        cmd1 = torch.zeros(1, device=dev)

        def one(state=state, scale=scale, cmd1=cmd1):
            guide = direction_guide(model, cmd1, scale) if scale > 0 else None
            state["x"] = model.transition.sample(state["x"], None, guide=guide)
            model.decode(state["x"])

        with _one_thread(dev), torch.no_grad():
            fps = frames_per_second(one, 30)
        rows.append(
            {
                "guide_scale": scale,
                "TE_deg": round(sum(te) / len(te), 2),
                "TE_x_deg": round(sum(te_x) / len(te_x), 2),
                "FD": round(sum(fd) / len(fd), 1),
                "fps": round(fps, 1),
            }
        )
    return rows


def _x_direction_error(model, r: Rollout, start: StartPose, cmd: Tensor, settle: int) -> float:
    """Degrees between the facing direction of the first horizon in x-hat and the command."""
    feats = r.features  # (C, K, F, D)
    C = feats.shape[0]
    h0 = torch.as_tensor(start.heading, dtype=torch.float32).reshape(C, 1, 1)
    heading = h0 + torch.cumsum(feats[..., 2], dim=-1)
    x = model.x_of(r.normalized.to(model.xz_mean.device)).cpu()  # (C, K, F, 12)
    n_h = len(model.config.horizons)
    d = x[..., 2 * n_h : 2 * n_h + 2]
    facing = heading + torch.atan2(d[..., 1], d[..., 0])
    err = wrap_angle(facing - cmd.reshape(C, 1, 1))[..., settle:].abs()
    return float(err.mean() * 180 / math.pi)
