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
The loop itself (resume, EMA, log, atomic checkpoints) is the one of :mod:`minimdm.training`,
shared with A-MDM; this module holds what is CAMDM's own: the data, the batches and the loss of
eq. 4, the evaluation and the checkpoint's metadata.

``minimdm camdm train configs/camdm.yaml`` runs it from the command line (into ``runs/camdm/``;
``--ship`` replaces the shipped ``checkpoints/camdm/``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from minimdm.checkpoint import Checkpoint, CheckpointMismatchError, load_checkpoint
from minimdm.diffusion import NoiseSchedule, diffusion_loss
from minimdm.files import RunLock
from minimdm.motion.features import Normalizer
from minimdm.motion.mirror import mirror_clips
from minimdm.motion.skeleton import Skeleton
from minimdm.nn import cosine_lr
from minimdm.training import Recipe, StepOut, start_training, train_loop
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
    """Windows and normalizers (fitted on unsmoothed trajectories) from labelled clips (and
    their mirror images with ``config.mirror``); the styles are the clips' ``labels["style"]``,
    sorted; ``heldout`` clips of known styles give the held-out loss."""
    if config.mirror:
        clips = list(clips) + mirror_clips(clips)
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
    held_out = bank(test) if test else None
    norms = Normalizer.fit(windows.flatten(1)), Normalizer.fit(traj.flatten(1))
    return TrainData(data, held_out, layout, skeleton, *norms, [c.name for c in clips])


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


def window_weights(style: Tensor, balance: float) -> Tensor | None:
    """Sampling weights of the windows ``(W,)``: each counts (windows of its style)^-balance,
    so that at ``balance`` 1 every style is drawn equally often. None at 0 (uniform draws)."""
    if balance == 0:
        return None
    counts = torch.bincount(style).double()
    return counts[style] ** -balance


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
    callback: Callable[[int, dict[str, Any]], None] | None = None,
) -> Checkpoint:
    """Train CAMDM; the checkpoint (EMA weights), its training state and ``log.jsonl`` go to
    ``out_dir``. ``data`` replaces the corpus (tests pass tiny windows). ``callback(step,
    record)`` runs after every step; raising from it stops the run (e.g. to simulate a kill)."""
    out_dir = check_output_dir("out_dir", out_dir)
    with threads(num_threads), RunLock(out_dir, (metadata or {}).get("command")):  # one run
        return _train(config, Path(out_dir), data, resume, progress, metadata or {}, callback)


def _train(
    config: CAMDMTrainConfig,
    out_dir: Path,
    data: TrainData | None,
    resume: bool,
    progress: bool,
    metadata: dict[str, Any],
    callback: Callable[[int, dict[str, Any]], None] | None,
) -> Checkpoint:
    """The CAMDM parts (batches, eq. 4, evaluation, metadata) on the shared loop."""
    device = torch.device(config.device)
    data = data or prepare_data(config)
    L = data.layout
    schedule = NoiseSchedule(config.schedule, config.T, device=device)
    state = start_training(
        config,
        out_dir,
        lambda: CAMDM(config.model_config(L.dim, len(L.styles))).to(device),
        torch.Generator(),  # on the CPU: a GPU run draws the CPU run's batches
        resume=resume,
        resumable=_RESUMABLE,
    )
    sigmas = [0.0, 0.0, 5.0, 10.0] if config.smooth_sigmas is None else list(config.smooth_sigmas)
    weights = window_weights(data.bank.style, config.style_balance)

    def batch_loss(step: int) -> StepOut:
        gen = state.generator
        if weights is None:
            idx = torch.randint(len(data.bank), (config.batch_size,), generator=gen)
        else:
            idx = torch.multinomial(weights, config.batch_size, replacement=True, generator=gen)
        x0, cond = make_batch(data, idx, sigmas, gen)
        loss, terms = camdm_loss(
            state.model, schedule, x0.to(device), _to(cond, device), data, config, gen
        )
        return StepOut(loss, terms=terms)

    recipe = Recipe(
        name="camdm",
        learning_rate=lambda step: cosine_lr(
            step, config.total_steps, config.lr, config.lr_min, config.warmup_steps
        ),
        batch_loss=batch_loss,
        evaluate=_evaluator(config, data, schedule, device),
        metadata=_metadata(config, data, metadata),
        device=str(device),
        record_segments=False,  # CAMDM's model.json has not recorded them
        state_order=("step", "model", "optimizer", "ema", "generator"),  # as its files have it
    )
    train_loop(config, out_dir, state, recipe, progress=progress, callback=callback)
    return load_checkpoint(out_dir, device=device)


def _evaluator(
    config: CAMDMTrainConfig, data: TrainData, schedule: NoiseSchedule, device: torch.device
) -> Callable[[torch.nn.Module, int], dict[str, float]]:
    """The loss of eq. 4 on 256 fixed windows of the training takes (``eval_loss``) and of the
    held-out takes (``heldout_loss``), unsmoothed, with draws of its own generator."""
    eval_idx = torch.randperm(len(data.bank), generator=torch.Generator().manual_seed(1234))[:256]

    def evaluate(net: torch.nn.Module, step: int) -> dict[str, float]:
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

    return evaluate


def _metadata(config: CAMDMTrainConfig, data: TrainData, metadata: dict[str, Any]) -> dict:
    """What a CAMDM checkpoint records besides the config: layout, skeleton, normalizers..."""
    return {
        **metadata,
        "feature_layout": data.layout,
        "skeleton": data.skeleton,
        "normalizer": {"window": data.window_norm, "traj": data.traj_norm},
        "diffusion": {"schedule": config.schedule, "T": config.T, "predicts": "x0"},
        "data": {
            "corpus": config.corpus,
            "split": config.split,
            "clips": data.clip_names,
            "windows": len(data.bank),
        },
    }


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
