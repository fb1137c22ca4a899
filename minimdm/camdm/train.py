"""Training CAMDM (Chen et al. 2024, §3.2-3.3): the losses of eqs. 2-4 and past-motion dropout.

A batch is B windows of P + F frames of the training takes, each in the frame of its last past
frame (:mod:`minimdm.camdm.data`), normalized per frame and feature. The trajectory condition is
the window's own future root path, Gaussian-smoothed for a random share of the windows as the
official trainer does (the paths a spring controller draws are smooth). Each sample draws a level
t of the T-step schedule (CAMDM: T = 8), the model predicts the clean future from
:math:`x_t` (:func:`minimdm.diffusion.diffusion_loss` with x0-prediction), and the loss is eq. 4,

.. math:: \\mathcal L = \\lambda_{samp}\\|\\hat x_0 - x_0\\|^2 + \\lambda_{pos}\\|FK(\\hat x_0) -
          FK(x_0)\\|^2 + \\lambda_{foot}\\mathcal L_{foot} + \\lambda_{vel}\\mathcal L_{vel},

with the joint positions of eq. 3 by forward kinematics of the rest skeleton, in decimetres
(``fk_scale``: our x0 loss is on normalized features, the paper's on raw ones),
:math:`\\mathcal L_{foot}` the squared velocity of the feet where the data's feet rest (MDM),
and :math:`\\mathcal L_{vel}` the squared error of the joints' velocities. The past motion is
replaced by the learned null with probability ``p_drop_past`` (0.15, for eq. 5), the style by the
null style with ``p_drop_style`` (for the rejected CFG-S). All randomness comes from one
generator seeded by ``seed``; a run resumed from its training state continues bit for bit.

``minimdm camdm train configs/camdm.yaml`` runs it from the command line (into ``runs/camdm/``;
``--ship`` replaces the shipped ``checkpoints/camdm/``).
"""

from __future__ import annotations

import copy
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from minimdm.amdm.train import read_log
from minimdm.checkpoint import (
    Checkpoint,
    CheckpointMismatchError,
    checkpoint_paths,
    load_checkpoint,
    resume_training,
    save_checkpoint,
)
from minimdm.diffusion import NoiseSchedule, diffusion_loss
from minimdm.files import RunLock, atomic_write
from minimdm.motion.features import Normalizer
from minimdm.motion.skeleton import Skeleton
from minimdm.nn import cosine_lr, ema_update, optimizer_step, set_lr
from minimdm.utils import num_threads as threads
from minimdm.validate import check_output_dir

from .data import (
    LOCOMOTION,
    CAMDMLayout,
    WindowBank,
    frame_positions,
    smooth_paths,
    trajectory_of,
    world_frames,
)
from .model import CAMDM, Conditions
from .train_config import CAMDMTrainConfig, load_train_config

__all__ = [
    "CAMDMTrainConfig",
    "load_train_config",
    "load_clips",
    "train_camdm",
    "TrainData",
    "prepare_data",
    "data_from_clips",
    "load_camdm",
    "camdm_loss",
]


def load_clips(corpus: str, split: str | None, fps: float, contents: list[str] | None) -> list:
    """The labelled takes of ``corpus`` with one of ``contents`` (default: locomotion)."""
    from minimdm.motion.corpora import load_motion

    wanted = set(contents or LOCOMOTION)
    clips = [
        c for c in load_motion(corpus, split=split, fps=fps) if c.labels.get("content") in wanted
    ]
    if not clips:
        raise ValueError(
            f"corpus {corpus!r} (split {split}) has no takes of contents {sorted(wanted)}"
        )
    if any("style" not in c.labels for c in clips):
        raise ValueError(f"corpus {corpus!r} has takes without a style label; CAMDM needs them")
    return clips


@dataclass
class TrainData:
    """Windows, normalizers and what a checkpoint records about them."""

    bank: WindowBank
    heldout: WindowBank | None
    layout: CAMDMLayout
    skeleton: Skeleton
    window_norm: Normalizer
    """Per frame and feature of the (P + F) D window."""
    traj_norm: Normalizer
    """Per point and component of the F x 4 trajectory."""
    clip_names: list[str]


def prepare_data(config: CAMDMTrainConfig) -> TrainData:
    """Load the takes the config names (the test takes too, for the held-out loss), cut the
    windows and fit the normalizers."""
    clips = load_clips(config.corpus, config.split, config.fps, config.contents)
    test = None
    if config.split == "train":
        test = load_clips(config.corpus, "test", config.fps, config.contents)
    return data_from_clips(clips, config, test)


def data_from_clips(
    clips: list, config: CAMDMTrainConfig, heldout: list | None = None
) -> TrainData:
    """Windows and normalizers (fitted on unsmoothed trajectories) from labelled clips; the
    styles are the clips' ``labels["style"]``, sorted; ``heldout`` clips of known styles give
    the held-out loss."""
    styles = tuple(sorted({c.labels["style"] for c in clips}))
    skeleton = clips[0].skeleton  # actors' bone lengths differ; the topology does not
    layout = CAMDMLayout(tuple(skeleton.names), styles, config.fps, config.past, config.future)

    def bank(cs: list) -> WindowBank:
        return WindowBank(
            [world_frames(c) for c in cs], [styles.index(c.labels["style"]) for c in cs], layout
        )

    test = [c for c in heldout or [] if c.labels["style"] in styles]
    data = bank(clips)
    windows, _ = data.batch(torch.arange(len(data)), skeleton.lateral_axis)  # (W, P + F, D)
    traj = _trajectory(windows, layout, skeleton)
    return TrainData(
        data, bank(test) if test else None, layout, skeleton, Normalizer.fit(windows.flatten(1)),
        Normalizer.fit(traj.flatten(1)), [c.name for c in clips],
    )  # fmt: skip


def _trajectory(windows: Tensor, layout: CAMDMLayout, skeleton: Skeleton) -> Tensor:
    return trajectory_of(windows[:, layout.past :], skeleton.lateral_axis)  # (B, F, 4)


def make_batch(
    data: TrainData, idx: Tensor, sigmas: list[float], generator: torch.Generator, bank=None
) -> tuple[Tensor, Conditions]:
    """Normalized clean futures ``(B, F, D)`` and their conditions for windows ``idx``."""
    bank = bank or data.bank
    L = data.layout
    windows, style = bank.batch(idx, data.skeleton.lateral_axis)  # (B, P + F, D)
    traj = _trajectory(windows, L, data.skeleton)
    if any(s > 0 for s in sigmas):  # smooth the path, measured from the reference again
        pick = torch.randint(len(sigmas), (len(idx),), generator=generator)
        sigma = torch.tensor(sigmas, dtype=torch.float32)[pick]
        path = smooth_paths(windows[..., :2], sigma)  # (B, P + F, 2)
        traj = traj.clone()
        traj[..., :2] = (path - path[:, L.past - 1 : L.past])[:, L.past :]
    w = data.window_norm.normalize(windows.flatten(1)).view_as(windows)
    tr = data.traj_norm.normalize(traj.flatten(1)).view_as(traj)
    return w[:, L.past :], Conditions(w[:, : L.past], style, tr)


def camdm_loss(
    model: torch.nn.Module,
    schedule: NoiseSchedule,
    x0: Tensor,
    cond: Conditions,
    data: TrainData,
    config: CAMDMTrainConfig,
    generator: torch.Generator,
) -> tuple[Tensor, dict[str, float]]:
    """Eq. 4 on a batch of clean futures ``x0`` (B, F, D), normalized; returns the loss and its
    terms. The condition dropout is drawn here, before the diffusion loss draws its levels."""
    B = x0.shape[0]
    keep_past = torch.rand(B, generator=generator) >= config.p_drop_past
    keep_style = torch.rand(B, generator=generator) >= config.p_drop_style
    cond = Conditions(cond.past, cond.style, cond.traj, keep_past, keep_style)
    l_samp, x0_hat = diffusion_loss(model, schedule, x0, cond, generator, predicts="x0")  # eq. 2
    P = data.layout.past
    norm = data.window_norm
    mean = norm.mean.view(-1, x0.shape[-1])[P:].to(x0)  # (F, D)
    std = norm.std.view(-1, x0.shape[-1])[P:].to(x0)
    k = config.fk_scale
    pos_hat = k * frame_positions(x0_hat * std + mean, data.skeleton)  # (B, F, J, 3)
    pos = k * frame_positions(x0 * std + mean, data.skeleton)
    l_pos = ((pos_hat - pos) ** 2).sum(-1).mean()  # eq. 3
    vel_hat, vel = pos_hat.diff(dim=1), pos.diff(dim=1)  # (B, F - 1, J, 3)
    l_vel = ((vel_hat - vel) ** 2).sum(-1).mean()
    feet = _feet(data.skeleton)
    rest = vel[:, :, feet].norm(dim=-1) < k * config.contact_speed  # (B, F - 1, n_feet)
    l_foot = ((vel_hat[:, :, feet] ** 2).sum(-1) * rest).mean()
    loss = (
        config.w_samp * l_samp
        + config.w_pos * l_pos
        + config.w_foot * l_foot
        + config.w_vel * l_vel
    )
    terms = {"samp": l_samp.item(), "pos": l_pos.item(), "foot": l_foot.item(), "vel": l_vel.item()}
    return loss, terms


def _feet(skeleton: Skeleton) -> list[int]:
    """The foot joints and their children (toes)."""
    out = []
    for f in skeleton.foot_indices:
        out += [f, *skeleton.children(f)]
    return out


def train_camdm(
    config: CAMDMTrainConfig,
    out_dir: str | os.PathLike,
    *,
    data: TrainData | None = None,
    resume: bool = True,
    progress: bool = True,
    num_threads: int | None = None,
    metadata: dict[str, Any] | None = None,
) -> Checkpoint:
    """Train CAMDM; the checkpoint (EMA weights), its training state and ``log.jsonl`` go to
    ``out_dir``. ``data`` replaces the corpus (tests pass tiny windows)."""
    out_dir = check_output_dir("out_dir", out_dir)
    with threads(num_threads), RunLock(out_dir, (metadata or {}).get("command")):  # one run
        return _train(config, Path(out_dir), data, resume, progress, metadata or {})


def _train(config, out_dir, data, resume, progress, metadata) -> Checkpoint:
    device = torch.device(config.device)
    data = data or prepare_data(config)
    L = data.layout
    schedule = NoiseSchedule(config.schedule, config.T, device=device)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = CAMDM(config.model_config(L.dim, len(L.styles))).to(device)
    ema = copy.deepcopy(model).eval() if config.ema_decay > 0 else None
    params = list(model.parameters())
    opt = torch.optim.Adam(params, lr=config.lr)
    gen = torch.Generator().manual_seed(config.seed)
    sigmas = [0.0, 0.0, 5.0, 10.0] if config.smooth_sigmas is None else list(config.smooth_sigmas)
    paths = checkpoint_paths(out_dir)
    step, prior_seconds = 0, 0.0
    if resume:
        step, prior_seconds = resume_training(
            out_dir, asdict(config), model, opt, gen, ema, resumable=_RESUMABLE
        )
    meta_base = {
        **metadata,
        "config": asdict(config),
        "config_file": config.config_file,
        "feature_layout": L,
        "skeleton": data.skeleton,
        "normalizer": {"window": data.window_norm, "traj": data.traj_norm},
        "diffusion": {"schedule": config.schedule, "T": config.T, "predicts": "x0"},
        "ema": ema is not None,
        "data": {"corpus": config.corpus, "split": config.split, "clips": data.clip_names,
                 "windows": len(data.bank)},
    }  # fmt: skip

    def save(at: int) -> None:
        state = {
            "step": at, "model": model.state_dict(), "optimizer": opt.state_dict(),
            "ema": ema.state_dict() if ema is not None else None, "generator": gen.get_state(),
        }  # fmt: skip
        seconds = round(prior_seconds + time.perf_counter() - t0, 1)
        meta = dict(meta_base, step=at, train_seconds=seconds)
        save_checkpoint(out_dir, ema if ema is not None else model, meta, optimizer_state=state)

    eval_idx = torch.randperm(len(data.bank), generator=torch.Generator().manual_seed(1234))[:256]

    def evaluate() -> dict[str, float]:
        net = ema if ema is not None else model
        g = torch.Generator().manual_seed(config.seed + 1)
        out = {}
        banks = {"eval_loss": (data.bank, eval_idx)}
        if data.heldout is not None:
            hidx = torch.randperm(len(data.heldout), generator=torch.Generator().manual_seed(1234))
            banks["heldout_loss"] = (data.heldout, hidx[:256])
        with torch.no_grad():
            for name, (bank, idx) in banks.items():
                x0, cond = make_batch(data, idx, [0.0], g, bank)
                loss, _ = camdm_loss(
                    net, schedule, x0.to(device), _to(cond, device), data, config, g
                )
                out[name] = float(loss)
        return out

    log_path = out_dir / "log.jsonl"
    out_dir.mkdir(parents=True, exist_ok=True)
    if log_path.exists():  # drop records past the resumed step (and a line torn by a kill)
        keep = [ln for ln, rec in read_log(log_path) if rec["step"] <= step]
        atomic_write(log_path, "".join(ln + "\n" for ln in keep))

    def log(rec: dict) -> None:
        with open(log_path, "a") as f:
            f.write(json.dumps(rec) + "\n")

    model.train()
    t0 = time.perf_counter()
    running: dict[str, float] = {}
    n = 0
    with tqdm(total=config.total_steps, initial=step, disable=not progress, desc="camdm") as bar:
        while step < config.total_steps:
            lr = cosine_lr(step, config.total_steps, config.lr, config.lr_min, config.warmup_steps)
            set_lr(opt, lr)
            idx = torch.randint(len(data.bank), (config.batch_size,), generator=gen)
            x0, cond = make_batch(data, idx, sigmas, gen)
            loss, terms = camdm_loss(
                model, schedule, x0.to(device), _to(cond, device), data, config, gen
            )
            if not torch.isfinite(loss):
                raise FloatingPointError(f"training loss became {loss.item()} at step {step}")
            optimizer_step(opt, loss, params, config.grad_clip)
            if ema is not None:
                ema_update(ema, model, config.ema_decay, step)
            step += 1
            n += 1
            for k, v in {"loss": loss.item(), **terms}.items():
                running[k] = running.get(k, 0.0) + v
            bar.update(1)
            last = step == config.total_steps
            if last or step % config.log_interval == 0:
                rec = {"step": step, **{k: v / n for k, v in running.items()}, "lr": lr}
                log(rec)
                bar.set_postfix(loss=f"{rec['loss']:.4f}")
                running, n = {}, 0
            if last or (config.eval_interval and step % config.eval_interval == 0):
                log({"step": step, **evaluate()})
                model.train()
            if last or (config.ckpt_interval and step % config.ckpt_interval == 0):
                save(step)
    if not paths.weights.exists():
        save(step)
    return load_checkpoint(out_dir, device=device)


_RESUMABLE = {
    "total_steps",
    "eval_interval",
    "ckpt_interval",
    "log_interval",
    "device",
    "config_file",
}


def _to(cond: Conditions, device: torch.device) -> Conditions:
    return Conditions(cond.past.to(device), cond.style.to(device), cond.traj.to(device))


def load_camdm(
    path: str | os.PathLike,
    expected_skeleton: Skeleton | dict | None = None,
    expected_styles: list[str] | tuple[str, ...] | None = None,
    device: torch.device | str = "cpu",
) -> Checkpoint:
    """Load a CAMDM checkpoint; one made for another skeleton or another style set is refused
    with :class:`~minimdm.checkpoint.CheckpointMismatchError` naming both."""
    ckpt = load_checkpoint(path, expected_skeleton=expected_skeleton, device=device)
    if ckpt.kind != "camdm":
        raise CheckpointMismatchError(
            f"checkpoint {ckpt.paths.weights} holds a {ckpt.kind!r} model, not a CAMDM ('camdm')"
        )
    styles = list((ckpt.feature_layout or {}).get("styles", []))
    if expected_styles is not None and list(expected_styles) != styles:
        raise CheckpointMismatchError(
            f"checkpoint {ckpt.paths.weights} was made for another style set: the checkpoint's "
            f"styles are {styles}, the expected styles are {list(expected_styles)}"
        )
    return ckpt
