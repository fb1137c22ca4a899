"""The study harnesses of chapter 8's motion tables: AAMDM against A-MDM (AAMDM §4.1).

:func:`motion_comparison` rolls out A-MDM at 5 (DDIM) and at all T steps and AAMDM (3 + 2) from
the same initial frames and scores them (AAMDM Table 1 on our data); :func:`dataset_quality` is
the data's own row; :func:`guidance_study` measures root-direction control (AAMDM §3.5, eq. 13)
per guidance scale; :func:`frames_per_second` times one character's rollout (batch 1), the
interactive setting. The algorithms they call live in :mod:`minimdm.aamdm.eval`.
"""

from __future__ import annotations

import math
import time
from typing import Any

import torch
from torch import Tensor

from minimdm.aamdm.eval import (
    direction_guide,
    heading_tracking_error,
    initial_states,
    local_poses,
    motion_quality,
    pose_diversity,
    pose_frechet_distance,
    rollout_aamdm,
)
from minimdm.aamdm.motion import AAMDMMotion
from minimdm.amdm.sampling import (
    FrameStep,
    Rollout,
    Sampler,
    autoregress,
    rollout,
)
from minimdm.motion import metrics
from minimdm.motion.features import StartPose
from minimdm.motion.skeleton import wrap_angle
from minimdm.utils import num_threads

__all__ = [
    "frames_per_second",
    "motion_comparison",
    "dataset_quality",
    "locomotion_clips",
    "guidance_study",
]


def frames_per_second(step: FrameStep, x0: Tensor, n_frames: int = 60, warmup: int = 5) -> float:
    """Frames per second of a rollout of ``step`` from ``x0`` (one character, batch 1) on the
    one rollout loop (:func:`~minimdm.amdm.sampling.autoregress`), best of two passes."""
    autoregress(step, x0, warmup)
    best = float("inf")
    for _ in range(2):
        t0 = time.perf_counter()
        autoregress(step, x0, n_frames)
        best = min(best, time.perf_counter() - t0)
    return n_frames / best


def _amdm_stepper(ckpt: Any, steps: int | None, eta: float, device: torch.device):
    """``(step(f, cond) -> frame, normalizer)`` for an A-MDM checkpoint, without randomness."""
    sampler = Sampler.load(ckpt, steps=steps, eta=eta, device=device)

    def step(f: int, cond: Tensor) -> Tensor:
        return sampler.frame(cond, None)

    return step, sampler.normalizer


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
    names: tuple[str, ...] | None = None,
    include_unpolished: bool = True,
) -> tuple[list[dict], dict[str, Rollout]]:
    """A-MDM at 5 (DDIM) and at all T steps vs AAMDM (3 + 2), in one run (AAMDM Table 1).

    Every method rolls out ``n_samples`` futures of ``n_frames`` from the same initial frames
    (:func:`initial_states` of ``names``) with the same seed, then :func:`motion_quality` scores
    them and :func:`frames_per_second` times one character (network calls plus decoding a
    pose; the CPU runs one thread for batch 1). ``amdm`` is a loaded A-MDM
    :class:`~minimdm.checkpoint.Checkpoint`. Returns the rows and the rollouts by method name.
    """
    dev = torch.device(device)
    sk = data["skeleton"]
    init = initial_states(data, names)
    data_poses = local_poses(torch.cat(data["y"]), len(sk))
    all_pos = torch.cat([torch.as_tensor(c.positions) for c in data["clips"]])
    foot = metrics.foot_contact_offsets(all_pos, sk.foot_indices)
    T = int(amdm.diffusion.get("T", 0))
    aamdm = aamdm.to(dev).eval()
    rows, rolls = [], {}
    methods: list[tuple[str, Any]] = [(f"amdm{s or T}", s) for s in amdm_steps]
    methods += [("aamdm", None)] + ([("aamdm_3+0", 0)] if include_unpolished else [])
    for name, arg in methods:
        g = torch.Generator(dev).manual_seed(seed)
        t0 = time.perf_counter()
        if name.startswith("amdm"):
            r = rollout(
                amdm,
                init["y"],
                n_frames,
                n_samples,
                steps=arg,
                generator=g,
                start_pose=init["start"],
                eta=eta,
                device=dev,
            )
            one, norm = _amdm_stepper(amdm, arg, eta, dev)
            x0 = norm.normalize(init["y"][:1]).to(dev)
            calls = arg or T
        else:
            r = rollout_aamdm(
                aamdm,
                init["y"],
                init["x"],
                n_frames,
                n_samples,
                g,
                start_pose=init["start"],
                T_adm=arg,
            )
            x0 = aamdm.encode(init["y"][:1].to(dev), init["x"][:1].to(dev))
            calls = aamdm.transition.T_gan + (aamdm.transition.T_adm if arg is None else arg)

            def one(f: int, xz: Tensor, arg=arg) -> Tensor:
                with torch.no_grad():
                    xz = aamdm.transition.sample(xz, None, T_adm=arg)
                    aamdm.decode(xz)
                return xz

        seconds = time.perf_counter() - t0
        with num_threads(1 if dev.type == "cpu" else None):
            fps = frames_per_second(one, x0, fps_frames)
        quality = motion_quality(r, sk, data_poses, foot, init["bone_lengths"])
        row = {"method": name, "network_calls": calls, **quality}
        row.update(fps=fps, rollout_s=seconds)
        rows.append({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()})
        rolls[name] = r
    return rows, rolls


def dataset_quality(data: dict) -> dict[str, float]:
    """The data's own DIV and the metrics of its clips (the target row of the table).

    FS and Jnt.Accel are the means over the clips weighted by their lengths; Bone.Err the mean
    over all frames.
    """
    sk = data["skeleton"]
    poses = local_poses(torch.cat(data["y"]), len(sk))
    pos = [torch.as_tensor(c.positions, dtype=torch.float64) for c in data["clips"]]
    foot = metrics.foot_contact_offsets(torch.cat(pos), sk.foot_indices)
    per_clip = []
    for p, c in zip(pos, data["clips"], strict=True):  # each clip against its own actor's bones
        bones = metrics.skeleton_bone_lengths(c.skeleton.offsets, sk.parents)
        per_clip.append(
            metrics.motion_metrics(p, sk.parents, sk.foot_indices, bones, foot_offset=foot)
        )
    n = sum(len(p) for p in pos)
    w = [len(p) / n for p in pos]

    def mean(key: str) -> float:
        return sum(wi * m[key] for wi, m in zip(w, per_clip, strict=True))

    return {
        "FS": mean("FS"),
        "Bone.Err": mean("Bone.Err"),
        "Jnt.Accel": mean("Jnt.Accel"),
        "DIV": pose_diversity(poses),
    }


def locomotion_clips(data: dict, contents: tuple[str, ...] = ("walk", "run")) -> tuple[str, ...]:
    """The first clip of each content: by ``labels["content"]`` for a corpus, by name otherwise."""
    clips = data["clips"]
    names = []
    for content in contents:
        match = [c.name for c in clips if (c.labels or {}).get("content", c.name) == content]
        if not match:
            raise ValueError(f"no clip with content {content!r} among {len(clips)} clips")
        names.append(match[0])
    return tuple(names)


def guidance_study(
    model: AAMDMMotion,
    data: dict,
    turns_deg: tuple[float, ...] = (90.0, -90.0, 180.0),
    scales: tuple[float, ...] = (0.0, 0.5, 2.0),
    names: tuple[str, ...] | None = None,
    n_frames: int = 150,
    n_samples: int = 4,
    settle: int = 45,
    seed: int = 0,
    device: str = "cpu",
) -> list[dict]:
    """Root-direction control (AAMDM §3.5, eq. 13): heading tracking error per guidance scale.

    From each initial frame of ``names`` (default: :func:`locomotion_clips`, a walk and a run),
    the command is the start heading turned by each of
    ``turns_deg``; ``TE`` is the mean absolute heading error in degrees after ``settle`` frames
    (AAMDM's TE-UC on the realised root heading), ``TE_x`` the error of the facing directions
    in the generated :math:`\\hat x` (the paper's :math:`|\\bar x - \\hat x|`, in degrees), and
    ``fps`` the speed for one character. Scale 0 is the unguided model.
    """
    dev = torch.device(device)
    model = model.to(dev).eval()
    init = initial_states(data, names or locomotion_clips(data))
    sk = data["skeleton"]
    data_poses = local_poses(torch.cat(data["y"]), len(sk))
    rows = []
    for scale in scales:
        te, te_x, fd = [], [], []
        for turn in turns_deg:
            cmd = init["start"].heading.float() + math.radians(turn)  # (C,)
            g = torch.Generator(dev).manual_seed(seed)
            r = rollout_aamdm(
                model,
                init["y"],
                init["x"],
                n_frames,
                n_samples,
                g,
                start_pose=init["start"],
                direction=cmd,
                guide_scale=scale,
            )
            te.append(heading_tracking_error(r, init["start"], cmd, settle))
            te_x.append(_x_direction_error(model, r, init["start"], cmd, settle))
            fd.append(pose_frechet_distance(local_poses(r.features, len(sk)), data_poses))
        x0 = model.encode(init["y"][:1].to(dev), init["x"][:1].to(dev))
        cmd1 = torch.zeros(1, device=dev)

        def one(f: int, xz: Tensor, scale=scale, cmd1=cmd1) -> Tensor:
            guide = direction_guide(model, cmd1, scale) if scale > 0 else None
            xz = model.transition.sample(xz, None, guide=guide)
            model.decode(xz)
            return xz

        with num_threads(1 if dev.type == "cpu" else None), torch.no_grad():
            fps = frames_per_second(one, x0, 30)
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
