"""Training A-MDM and its baselines with scheduled sampling (A-MDM §3.2).

One trainer serves three models, chosen by :attr:`TrainConfig.model_kind`:

* ``"amdm"`` — the A-MDM denoiser (:class:`~minimdm.amdm.models.MLPDenoiser`) trained with the DDPM
  loss of eq. 3 (:func:`~minimdm.diffusion.diffusion_loss`);
* ``"mse"`` — the deterministic next-frame regressor (:class:`~minimdm.amdm.models.MLPRegressor`),
  trained with MSE;
* ``"mvae"`` — the MVAE-style conditional VAE (:class:`~minimdm.amdm.models.MVAE`), trained with
  reconstruction + β-KL.

All three see the same data and the same protocol. A batch is ``B`` windows of ``N_r + 1``
consecutive (normalized) frames. Frame ``f = 1..N_r`` is predicted from a condition: the
ground-truth frame ``f - 1`` (teacher forcing) or the model's own reconstruction of frame
``f - 1`` from the previous step of the window, detached (student forcing). Each sample makes
that choice with the probability :func:`student_probability`, which follows the MVAE schedule:
0 for ``teacher_steps``, then a linear ramp over ``ramp_steps`` to 1. For A-MDM the
reconstruction is :math:`\\hat x_f^0` at the randomly drawn noise level of the loss, as in the
paper ("use the reconstructed :math:`\\hat x_f^t` as the next frame").

The loop is deterministic: all its randomness (batches, noise levels, teacher/student coins)
comes from one :class:`torch.Generator` seeded by ``seed``, whose state is saved in every
checkpoint with the optimizer and the EMA weights; a run resumed from step k performs the same
step k + 1 as an uninterrupted one, bit for bit.
"""

from __future__ import annotations

import copy
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from minimdm import config as configs
from minimdm.amdm.models import MVAE, DenoiserConfig, MLPDenoiser, MLPRegressor, MVAEConfig
from minimdm.checkpoint import (
    Checkpoint,
    checkpoint_paths,
    load_checkpoint,
    load_train_state,
    save_checkpoint,
)
from minimdm.diffusion import (
    NoiseSchedule,
    clamp_share,
    clamp_x0,
    clip_bounds,
    data_range,
    diffusion_loss,
)
from minimdm.nn import cosine_lr, ema_update, set_lr
from minimdm.utils import num_threads as threads

__all__ = [
    "TrainConfig",
    "load_config",
    "student_probability",
    "learning_rate",
    "build_network",
    "frame_loss",
    "window_loss",
    "make_windows",
    "train_amdm",
    "TrainResult",
    "resolve_clip_x0",
    "checkpoint_training_frames",
    "checkpoint_clamp_share",
]

MODEL_KINDS = ("amdm", "mse", "mvae")


@dataclass
class TrainConfig:
    """Everything that defines a training run; ``configs/*.yaml`` load into it."""

    # ---- model
    model_kind: str = "amdm"
    """Which model: 'amdm' (diffusion), 'mse' (deterministic regressor) or 'mvae' (cond. VAE)."""
    width: int = 512
    """Hidden units per layer (A-MDM paper: 1024)."""
    depth: int = 6
    """Fully connected layers including the output layer (A-MDM paper: 10)."""
    time_dim: int = 128
    """Size of the sinusoidal diffusion-step embedding (amdm only)."""
    latent_dim: int = 32
    """Size of the MVAE latent z (mvae only)."""
    # ---- diffusion
    T: int = 40
    """Number of diffusion steps (A-MDM paper: 40)."""
    schedule: str = "cosine"
    """Noise schedule: 'cosine' or 'linear'."""
    predicts: str = "eps"
    """What the denoiser outputs: 'eps' (A-MDM eq. 3) or 'x0'."""
    # ---- optimisation
    lr: float = 3e-4
    """Adam learning rate at the start."""
    lr_min: float = 3e-5
    """Learning rate at the end of a cosine decay over total_steps (= lr: constant)."""
    grad_clip: float = 1.0
    """Clip the gradient norm to this value (0: no clipping)."""
    batch_size: int = 128
    """Windows per step."""
    total_steps: int = 2000
    """Optimizer steps in the whole run."""
    kl_beta: float = 0.2
    """Weight of the KL term per frame dimension (mvae only)."""
    # ---- scheduled sampling (A-MDM §3.2, MVAE-style)
    rollout: int = 4
    """N_r: frames predicted per window, each conditioned on the previous one."""
    teacher_steps: int = 500
    """Steps of pure teacher forcing (student probability 0)."""
    ramp_steps: int = 500
    """Steps over which the student probability rises linearly from 0 to 1."""
    clip_x0: float | str | None = "data"
    """Clamp x0 estimates when fed back and when sampling: 'data' (the per-feature range of the
    normalized training frames), a float c ([-c, c]), or None."""
    # ---- EMA, evaluation, checkpoints
    ema_decay: float = 0.999
    """Decay of the exponential moving average of the weights (0: no EMA)."""
    eval_interval: int = 500
    """Run the evaluation every this many steps (0: only at the end)."""
    eval_windows: int = 256
    """Held-in windows of the teacher-forced evaluation loss."""
    ckpt_interval: int = 500
    """Write a resumable checkpoint every this many steps (0: only at the end)."""
    log_interval: int = 50
    """Append the running training loss to log.jsonl every this many steps."""
    seed: int = 0
    """Seeds the initial weights and every random draw of training."""
    # ---- data
    fps: float = 30.0
    """Frame rate the clips are resampled to (A-MDM: 30 Hz)."""
    clips: list[str] | None = None
    """Names of the clips to train on (None: every humanoid clip of the data package)."""
    loop_frames: int | None = 150
    """Unroll looping clips to this many frames so windows cross the loop seam (None: 1 cycle)."""
    device: str = "cpu"
    """Where to train: 'cpu' or 'cuda'."""
    config_file: str | None = None
    """The YAML file this config came from (set by load_config; recorded in checkpoints)."""

    def __post_init__(self) -> None:
        if self.model_kind not in MODEL_KINDS:
            raise ValueError(f"model_kind must be one of {MODEL_KINDS}, got {self.model_kind!r}")
        for name in ("width", "depth", "T", "batch_size", "total_steps", "rollout"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.depth < 2:
            raise ValueError(f"depth must be >= 2, got {self.depth}")
        if self.teacher_steps < 0 or self.ramp_steps < 0:
            raise ValueError(
                f"teacher_steps and ramp_steps must be >= 0, got {self.teacher_steps}, "
                f"{self.ramp_steps}"
            )
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must lie in [0, 1), got {self.ema_decay}")


# Fields that may change between a checkpoint and a resumed run.
_RESUMABLE_CHANGES = {
    "total_steps",
    "eval_interval",
    "eval_windows",
    "ckpt_interval",
    "log_interval",
    "device",
    "config_file",
}


def load_config(path: str | os.PathLike) -> TrainConfig:
    """Read a YAML or TOML training config into a :class:`TrainConfig`.

    Unknown keys are an error and values take the field types (:func:`minimdm.config.load_config`).
    """
    return configs.load_config(path, TrainConfig)


def student_probability(config: TrainConfig, step: int) -> float:
    """Probability of feeding the model's own prediction at ``step`` (0-based).

    0 while ``step < teacher_steps``; then ``(step - teacher_steps) / ramp_steps`` up to 1.
    """
    if step < config.teacher_steps:
        return 0.0
    if config.ramp_steps == 0:
        return 1.0
    return min(1.0, (step - config.teacher_steps + 1) / config.ramp_steps)


def learning_rate(config: TrainConfig, step: int) -> float:
    """Cosine decay from ``lr`` to ``lr_min`` over ``total_steps`` (``minimdm.nn.cosine_lr``)."""
    return cosine_lr(step, config.total_steps, config.lr, config.lr_min)


def build_network(config: TrainConfig, x_dim: int) -> nn.Module:
    """The network of ``config.model_kind`` for frames of dimension ``x_dim``."""
    if config.model_kind == "amdm":
        dc = DenoiserConfig(
            x_dim, x_dim, config.width, config.depth, config.time_dim, config.predicts
        )
        return MLPDenoiser(dc)
    if config.model_kind == "mse":
        return MLPRegressor(x_dim, x_dim, config.width, config.depth)
    return MVAE(MVAEConfig(x_dim, x_dim, config.latent_dim, config.width, config.depth))


def frame_loss(
    model: nn.Module,
    x: Tensor,
    cond: Tensor,
    generator: torch.Generator | None,
    kind: str = "amdm",
    schedule: NoiseSchedule | None = None,
    predicts: str = "eps",
    kl_beta: float = 0.2,
) -> tuple[Tensor, Tensor]:
    """Per-sample loss of predicting ``x`` (B, D) from ``cond`` (B, D), and the prediction.

    * amdm: the DDPM loss (A-MDM eq. 3); the prediction is :math:`\\hat x_0` at the drawn step.
    * mse: :math:`\\|f(x_{f-1}) - x_f\\|^2 / D`; the prediction is :math:`f(x_{f-1})`.
    * mvae: :math:`\\|\\hat x_f - x_f\\|^2 / D + \\beta\\,\\mathrm{KL}(q \\| \\mathcal N(0, I)) / D`
      with :math:`q = q(z | x_f, x_{f-1})`, the β-ELBO; the prediction is the reconstruction
      through the posterior.

    Returns ``(loss (B,), prediction (B, D))``.
    """
    if kind == "amdm":
        if schedule is None:
            raise ValueError("schedule is required for kind='amdm'")
        return diffusion_loss(model, schedule, x, cond, generator, predicts, reduce=False)
    if kind == "mse":
        pred = model(cond)
        return ((pred - x) ** 2).mean(1), pred
    if kind == "mvae":
        pred, mu, logvar = model(x, cond, generator)
        rec = ((pred - x) ** 2).mean(1)
        kl = -0.5 * (1 + logvar - mu**2 - logvar.exp()).sum(1)  # (B,)
        return rec + kl_beta * kl / x.shape[1], pred
    raise ValueError(f"kind must be one of {MODEL_KINDS}, got {kind!r}")


def window_loss(
    model: nn.Module,
    windows: Tensor,
    p_student: float,
    generator: torch.Generator | None,
    kind: str = "amdm",
    schedule: NoiseSchedule | None = None,
    predicts: str = "eps",
    kl_beta: float = 0.2,
    clip_x0: Any = None,
) -> tuple[Tensor, dict[str, float]]:
    """Scheduled-sampling loss over windows (B, N_r + 1, D) (A-MDM §3.2).

    Frame 0 of each window is the ground-truth start. Frame ``f >= 1`` is predicted from the
    condition ``c_f``: ``c_1 = x_0``; for ``f > 1`` each sample takes its own previous
    prediction ``\\hat x_{f-1}`` (detached) with probability ``p_student``, else the ground truth
    ``x_{f-1}``; a fed-back prediction is clamped to ``clip_x0``: None, a float ``c``
    (``[-c, c]``) or a per-feature range ``(lo, hi)`` (:func:`~minimdm.diffusion.clip_bounds`).

    For A-MDM the prediction fed back is the reconstruction :math:`\\hat x_0` at the noise level
    drawn for the loss, as in the paper. With eps-prediction it divides by
    :math:`\\sqrt{\\bar\\alpha_t}`, which is tiny at the noisiest levels: the clamp keeps it
    bounded, and x0-prediction avoids the division. Returns the mean
    loss over frames and samples, and the fraction of student conditions used. With
    ``p_student = 0`` all frames run as one batch.
    """
    if windows.dim() != 3 or windows.shape[1] < 2:
        raise ValueError(
            f"windows must have shape (B, N_r + 1 >= 2, D), got {tuple(windows.shape)}"
        )
    B, n1, D = windows.shape
    bounds = clip_bounds(clip_x0, D, windows.device, windows.dtype)
    kw = dict(kind=kind, schedule=schedule, predicts=predicts, kl_beta=kl_beta)
    if p_student <= 0:
        x = windows[:, 1:].reshape(B * (n1 - 1), D)  # (B N_r, D)
        cond = windows[:, :-1].reshape(B * (n1 - 1), D)
        loss, _ = frame_loss(model, x, cond, generator, **kw)
        return loss.mean(), {"student_frac": 0.0}
    cond = windows[:, 0]  # (B, D)
    losses, n_student = [], 0
    for f in range(1, n1):
        loss_f, pred = frame_loss(model, windows[:, f], cond, generator, **kw)
        losses.append(loss_f)
        if f + 1 < n1:
            pred = pred.detach()
            coin = torch.rand(B, generator=generator, device=windows.device) < p_student  # (B,)
            pred = clamp_x0(pred, bounds)
            n_student += int(coin.sum())
            cond = torch.where(coin[:, None], pred, windows[:, f])
    frac = n_student / (B * max(n1 - 2, 1))
    return torch.stack(losses).mean(), {"student_frac": frac}


def make_windows(features: Sequence[Tensor | np.ndarray], n: int) -> Tensor:
    """Every window of ``n + 1`` consecutive frames of every clip, stacked: (W, n + 1, D).

    Windows never cross clips (:class:`~minimdm.motion.features.WindowDataset`); clips shorter than
    ``n + 1`` frames contribute none.
    """
    from minimdm.motion.features import WindowDataset

    for i, a in enumerate(features):
        a = torch.as_tensor(a)
        if a.dim() != 2:
            raise ValueError(f"features[{i}] must have shape (F, D), got {tuple(a.shape)}")
        if not torch.isfinite(a).all():
            raise ValueError(f"features[{i}] must be finite, but it holds NaN/Inf")
    ds = WindowDataset(features, n)
    return torch.stack([ds[i] for i in range(len(ds))])  # (W, n + 1, D)


# --------------------------------------------------------------------------------------------
# The loop.


@dataclass
class TrainResult:
    """What :func:`train_amdm` returns."""

    checkpoint: Checkpoint
    """The final checkpoint, loaded (EMA weights when EMA is on)."""
    steps: int
    """Optimizer steps done in total."""
    seconds: float
    """Wall time of this call's training loop."""
    steps_per_second: float
    """Speed of this call's training loop."""
    history: list[dict] = field(default_factory=list)
    """The log records of this call (training loss, evaluations)."""


def _load_data(config: TrainConfig) -> dict[str, Any]:
    """Load the clips, encode them (A-MDM §3.1) and fit the normalizer: the real-data path."""
    from minimdm.motion import data, features

    clips = data.load_clips(fps=config.fps, loop_frames=config.loop_frames, names=config.clips)
    arrays = [features.encode(c) for c in clips]  # [(F_i - 1, D)]
    normalizer = features.Normalizer.fit(arrays)
    return {
        "features": [normalizer.normalize(a) for a in arrays],
        "normalizer": normalizer,
        "skeleton": clips.skeleton,
        "layout": features.FeatureLayout.for_skeleton(clips.skeleton, config.fps),
        "clip_names": clips.names,
    }


def _config_diff(a: dict, b: dict) -> list[str]:
    keys = sorted((set(a) | set(b)) - _RESUMABLE_CHANGES)
    return [f"{k}: {a.get(k)!r} vs {b.get(k)!r}" for k in keys if a.get(k) != b.get(k)]


def train_amdm(
    config: TrainConfig,
    out_dir: str | os.PathLike,
    features: Sequence[Tensor | np.ndarray] | None = None,
    *,
    normalizer: Any = None,
    skeleton: Any = None,
    layout: Any = None,
    resume: bool = True,
    progress: bool = True,
    eval_fn: Callable[[nn.Module, int], dict[str, float]] | None = None,
    callback: Callable[[int, dict[str, float]], None] | None = None,
    num_threads: int | None = None,
    metadata: dict[str, Any] | None = None,
) -> TrainResult:
    """Train ``config.model_kind`` with scheduled sampling; checkpoints go to ``out_dir``.

    Args:
        config: the run.
        out_dir: folder of the checkpoint (``model.safetensors``, ``model.json``,
            ``model.train.safetensors``) and of ``log.jsonl``.
        features: in-memory training data instead of the clips named by the config: a list of
            normalized per-clip feature arrays (F_i, D). ``normalizer``, ``skeleton`` and
            ``layout`` are then only recorded in the checkpoint metadata (any of them may be
            None).
        resume: continue from ``out_dir``'s training state if there is one. The config must
            match the saved one except for total_steps and the intervals.
        progress: show a tqdm progress bar.
        eval_fn: ``eval_fn(model, step) -> {name: value}``, called with the EMA (or raw) model
            in eval mode every ``eval_interval`` steps and at the end, next to the built-in
            teacher-forced loss ``eval_loss``. It must not use the global RNG to stay resumable.
        callback: ``callback(step, record)`` after every optimizer step (``step`` counts
            finished steps); raising from it stops the run, e.g. to simulate an interruption.
        num_threads: torch CPU threads during the run (None: leave as is). On a shared 2-core
            machine 1 thread trained the book config 3-10x faster than 2.
        metadata: extra JSON-able facts stored in the checkpoint, e.g. the ``command`` that
            reproduces it (the CLI records it).
    """
    with threads(num_threads):
        args = (normalizer, skeleton, layout, resume, progress, eval_fn, callback, metadata)
        return _train(config, out_dir, features, *args)


def _train(
    config: TrainConfig,
    out_dir: str | os.PathLike,
    features: Sequence[Tensor | np.ndarray] | None,
    normalizer: Any,
    skeleton: Any,
    layout: Any,
    resume: bool,
    progress: bool,
    eval_fn: Callable[[nn.Module, int], dict[str, float]] | None,
    callback: Callable[[int, dict[str, float]], None] | None,
    metadata: dict[str, Any] | None,
) -> TrainResult:
    out_dir = Path(out_dir)
    device = torch.device(config.device)
    clip_names = None
    if features is None:
        loaded = _load_data(config)
        features, clip_names = loaded["features"], loaded["clip_names"]
        normalizer, skeleton, layout = loaded["normalizer"], loaded["skeleton"], loaded["layout"]
    windows = make_windows(features, config.rollout).to(device)  # (W, N_r + 1, D)
    clip_x0 = resolve_clip_x0(config.clip_x0, features)  # 'data': the frames' range
    x_dim = windows.shape[-1]
    schedule = NoiseSchedule(config.schedule, config.T, device=device)

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = build_network(config, x_dim).to(device)
    ema = copy.deepcopy(model).eval() if config.ema_decay > 0 else None
    for p in ema.parameters() if ema is not None else ():
        p.requires_grad_(False)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    gen = torch.Generator(device=device).manual_seed(config.seed)
    step = 0

    paths = checkpoint_paths(out_dir)
    if resume and paths.train.exists():
        meta, state = load_train_state(out_dir)
        diff = _config_diff(meta.get("config", {}), asdict(config))
        if diff:
            raise ValueError(
                f"cannot resume from {paths.train}: its config differs from this run's "
                f"(saved vs now): {'; '.join(diff)}. Use another out_dir or resume=False."
            )
        model.load_state_dict(state["model"])
        if ema is not None:
            ema.load_state_dict(state["ema"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"].to(torch.uint8))
        step = int(state["step"])

    metadata_base = {
        **(metadata or {}),
        "config": asdict(config),
        "config_file": config.config_file,
        "feature_layout": layout,
        "skeleton": skeleton,
        "normalizer": normalizer,
        "ema": ema is not None,
        "data": {"clips": clip_names, "fps": config.fps, "windows": int(windows.shape[0])},
    }
    if config.model_kind == "amdm":
        metadata_base["diffusion"] = {
            "schedule": config.schedule,
            "T": config.T,
            "predicts": config.predicts,
            "clip_x0": clip_x0,
        }

    def save(at_step: int) -> None:
        state = {
            "step": at_step,
            "model": model.state_dict(),
            "ema": ema.state_dict() if ema is not None else None,
            "optimizer": opt.state_dict(),
            "generator": gen.get_state(),
        }
        meta = dict(metadata_base, step=at_step)
        save_checkpoint(out_dir, ema if ema is not None else model, meta, optimizer_state=state)

    loss_kw = dict(
        kind=config.model_kind,
        schedule=schedule,
        predicts=config.predicts,
        kl_beta=config.kl_beta,
        clip_x0=clip_x0,
    )

    # Built-in evaluation: teacher-forced loss on fixed windows with its own generator.
    eval_gen = torch.Generator(device=device)
    eval_idx = torch.randperm(windows.shape[0], generator=torch.Generator().manual_seed(1234))
    eval_windows = windows[eval_idx[: config.eval_windows].to(device)]

    def evaluate(at_step: int) -> dict[str, float]:
        net = ema if ema is not None else model
        net.eval()
        eval_gen.manual_seed(config.seed + 1)
        with torch.no_grad():
            loss, _ = window_loss(net, eval_windows, 0.0, eval_gen, **loss_kw)
        out = {"eval_loss": float(loss)}
        if eval_fn is not None:
            out.update(eval_fn(net, at_step))
        model.train()
        return out

    log_path = out_dir / "log.jsonl"
    out_dir.mkdir(parents=True, exist_ok=True)
    if log_path.exists():  # drop records past the resumed step (an interrupted tail)
        keep = [ln for ln in log_path.read_text().splitlines() if json.loads(ln)["step"] <= step]
        log_path.write_text("".join(ln + "\n" for ln in keep))
    history: list[dict] = []

    def log(record: dict) -> None:
        history.append(record)
        with open(log_path, "a") as f:
            f.write(json.dumps(record) + "\n")

    model.train()
    start_step, t0 = step, time.perf_counter()
    with tqdm(
        total=config.total_steps, initial=step, disable=not progress, desc=config.model_kind
    ) as bar:
        running, n_running = 0.0, 0
        while step < config.total_steps:
            lr = learning_rate(config, step)
            set_lr(opt, lr)
            p = student_probability(config, step)
            B, W = config.batch_size, windows.shape[0]
            idx = torch.randint(W, (B,), generator=gen, device=device)
            loss, info = window_loss(model, windows[idx], p, gen, **loss_kw)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"training loss became {loss.item()} at step {step}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if config.grad_clip > 0:
                nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            opt.step()
            if ema is not None:
                ema_update(ema, model, config.ema_decay, step)
            step += 1
            running, n_running = running + loss.item(), n_running + 1
            record = {"step": step, "loss": loss.item(), "p_student": p, "lr": lr, **info}
            bar.update(1)
            last = step == config.total_steps
            if last or step % config.log_interval == 0:
                rec = {"step": step, "loss": running / n_running, "p_student": p, "lr": lr}
                log(rec)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", p=f"{p:.2f}")
                running, n_running = 0.0, 0
            if last or (config.eval_interval and step % config.eval_interval == 0):
                ev = evaluate(step)
                log({"step": step, **ev})
                record.update(ev)
            if last or (config.ckpt_interval and step % config.ckpt_interval == 0):
                save(step)
            if callback is not None:
                callback(step, record)
    seconds = time.perf_counter() - t0
    if step == start_step and not paths.weights.exists():
        save(step)
    done = step - start_step
    return TrainResult(
        checkpoint=load_checkpoint(out_dir, device=device),
        steps=step,
        seconds=seconds,
        steps_per_second=done / seconds if seconds > 0 and done else 0.0,
        history=history,
    )


# --------------------------------------------------------------------------------------------
# The x0 clamp: the training data's range


def resolve_clip_x0(clip_x0: Any, frames: Sequence[Tensor | np.ndarray]) -> Any:
    """A config's ``clip_x0`` made concrete for the normalized training ``frames``.

    ``"data"`` becomes the frames' per-feature range ``[[lo...], [hi...]]`` (JSON-able, what
    checkpoints store as ``diffusion.clip_x0``); None and floats stay; a pair is checked.
    """
    if clip_x0 == "data":
        lo, hi = data_range(frames)
        return [lo.tolist(), hi.tolist()]
    dim = torch.as_tensor(frames[0]).shape[-1]
    bounds = clip_bounds(clip_x0, dim)
    return [bounds[0].tolist(), bounds[1].tolist()] if isinstance(bounds, tuple) else bounds


def checkpoint_training_frames(ckpt: Checkpoint) -> Tensor:
    """The normalized frames (N, D) an A-MDM checkpoint was trained on, rebuilt from its metadata.

    The clips are loaded as the training loaded them (names, fps, loop unrolling), encoded, and
    normalized with the checkpoint's own statistics.
    """
    from minimdm.motion import data, features

    cfg, meta = ckpt.config, ckpt.metadata
    names = (meta.get("data") or {}).get("clips") or cfg.get("clips")
    clips = data.load_clips(
        fps=cfg.get("fps", 30.0), loop_frames=cfg.get("loop_frames", 150), names=names
    )
    if ckpt.normalizer is None:
        raise ValueError(f"checkpoint {ckpt.paths.weights} records no normalizer")
    norm = features.Normalizer.from_dict(ckpt.normalizer)
    return torch.cat([norm.normalize(features.encode(c)) for c in clips])  # (N, D)


def checkpoint_clamp_share(
    ckpt: Checkpoint, clip_x0: Any = "checkpoint", frames: Tensor | None = None
) -> float:
    """The share of a checkpoint's training frames that its x0 clamp would change.

    ``clip_x0="checkpoint"`` takes the checkpoint's ``diffusion.clip_x0``; pass another value
    (e.g. the old 5.0) to compare. ``frames`` default to :func:`checkpoint_training_frames`.
    A frame outside the clamp cannot come out of the sampler, so this should be 0.
    """
    if clip_x0 == "checkpoint":
        clip_x0 = (ckpt.metadata.get("diffusion") or {}).get("clip_x0")
    frames = checkpoint_training_frames(ckpt) if frames is None else frames
    return clamp_share(clip_x0, frames)
