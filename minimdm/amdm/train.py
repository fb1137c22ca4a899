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

``torchrun --nproc_per_node=N -m minimdm train CONFIG`` trains on N processes with DDP
(:mod:`minimdm.distributed`): each process draws ``batch_size / N`` windows from its own
generator, DDP averages the gradients, and rank 0 alone writes checkpoints and logs. A resumed
multi-process run reseeds each rank's generator from the step, so it continues cleanly but is
not bit-identical to an uninterrupted one.

The config is :class:`~minimdm.amdm.train_config.TrainConfig` (re-exported here with
:func:`load_config` and :func:`student_probability`); the losses are in
:mod:`minimdm.amdm.losses`; this module holds the loop.
"""

from __future__ import annotations

import copy
import json
import os
import platform
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel
from tqdm.auto import tqdm

from minimdm import distributed
from minimdm.amdm.losses import FrameGeometry, make_windows, window_loss
from minimdm.amdm.train_config import (
    TrainConfig,
    build_network,
    learning_rate,
    load_config,
    student_probability,
)
from minimdm.checkpoint import (
    Checkpoint,
    checkpoint_paths,
    load_checkpoint,
    load_train_state,
    resume_training,
    save_checkpoint,
)
from minimdm.diffusion import (
    NoiseSchedule,
    clamp_share,
    clip_bounds,
    data_range,
)
from minimdm.files import RunLock, atomic_write
from minimdm.motion.corpora import LOCOMOTION
from minimdm.nn import ema_update, optimizer_step, set_lr
from minimdm.utils import num_threads as threads
from minimdm.validate import InputError, InputTypeError, check_output_dir, describe

__all__ = [
    "TrainConfig",
    "load_config",
    "student_probability",
    "train_amdm",
    "TrainResult",
    "resolve_clip_x0",
    "read_log",
    "checkpoint_training_frames",
    "checkpoint_clamp_share",
]


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
    from minimdm.motion import features

    clips = _load_clips(config.corpus, config.split, config.fps, config.clips, config.loop_frames)
    arrays = [features.encode(c) for c in _with_mirrored(clips, config.mirror)]  # [(F_i - 1, D)]
    normalizer = features.Normalizer.fit(arrays)
    if config.feature_scale != 1.0:
        k = config.feature_scale  # the floor too: a barely varying feature gets k as well
        normalizer = features.Normalizer(normalizer.mean, normalizer.std / k, normalizer.floor / k)
    skeleton = clips[0].skeleton  # actors' bone lengths may differ; the topology may not
    heldout = None
    if config.split == "train":  # the corpus's test takes: a held-out loss during training
        test = _load_clips(config.corpus, "test", config.fps, None, config.loop_frames)
        heldout = [normalizer.normalize(features.encode(c)) for c in test]
    return {
        "heldout": heldout,
        "features": [normalizer.normalize(a) for a in arrays],
        "normalizer": normalizer,
        "skeleton": skeleton,
        "layout": features.FeatureLayout.for_skeleton(skeleton, config.fps),
        "clip_names": clips.names,
        "contents": [c.labels.get("content") for c in clips] * (2 if config.mirror else 1),
    }


def window_weights(
    lengths: Sequence[int], n: int, contents: Sequence[str | None], share: float
) -> Tensor:
    """Sampling weights (W,) of the windows :func:`make_windows` cuts from clips of these
    lengths (F_i - n windows each): locomotion windows get ``share`` in all, split equally
    among the locomotion contents present; the others get ``1 - share`` by count. The weights
    sum to 1. With no clip of either kind, the other kind gets everything."""
    if len(lengths) != len(contents):
        raise ValueError(f"{len(lengths)} clips but {len(contents)} content labels")
    counts = [max(0, int(f) - n) for f in lengths]
    loco = sorted({c for c, k in zip(contents, counts, strict=True) if c in LOCOMOTION and k})
    other = sum(k for c, k in zip(contents, counts, strict=True) if c not in LOCOMOTION)
    if not loco or not other:
        share = 1.0 if loco else 0.0
    per_content = {c: sum(k for d, k in zip(contents, counts, strict=True) if d == c) for c in loco}
    parts = []
    for c, k in zip(contents, counts, strict=True):
        if not k:
            continue
        w = share / len(loco) / per_content[c] if c in LOCOMOTION else (1 - share) / other
        parts.append(torch.full((k,), w, dtype=torch.float64))
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)


def _with_mirrored(clips: Any, mirror: bool) -> list:
    """The clips, followed by their mirror images when ``mirror`` (:mod:`minimdm.motion.mirror`)."""
    from minimdm.motion.mirror import mirror_clips

    clips = list(clips)
    return clips + mirror_clips(clips) if mirror else clips


def _load_clips(corpus: str, split: str | None, fps: float, names: Any, loop_frames: Any) -> Any:
    """The clips a config names (:func:`minimdm.motion.corpora.load_motion`)."""
    from minimdm.motion.corpora import load_motion

    return load_motion(corpus, split=split, fps=fps, names=names, loop_frames=loop_frames)


# Fields that may change between a checkpoint and a resumed run.
_RESUMABLE_CHANGES = {
    "total_steps",
    "eval_interval",
    "eval_windows",
    "ckpt_interval",
    "log_interval",
    "storage",
    "device",
    "config_file",
}


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
            teacher-forced losses ``eval_loss`` (training takes) and ``heldout_loss`` (the test
            takes, when ``config.split`` is "train"). It must not use the global RNG to stay
            resumable.
        callback: ``callback(step, record)`` after every optimizer step (``step`` counts
            finished steps); raising from it stops the run, e.g. to simulate an interruption.
        num_threads: torch CPU threads during the run (None: leave as is). On a shared 2-core
            machine 1 thread trained the book config 3-10x faster than 2.
        metadata: extra JSON-able facts stored in the checkpoint, e.g. the ``command`` that
            reproduces it (the CLI records it).
    """
    if not isinstance(config, TrainConfig):
        raise InputTypeError(f"config must be a TrainConfig, got {describe(config)}")
    out_dir = check_output_dir("out_dir", out_dir)  # before any data is loaded or step taken
    with threads(num_threads), RunLock(out_dir, (metadata or {}).get("command")):  # one run
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
    world = distributed.setup(config.device)  # one process, or one of torchrun's N
    if config.batch_size % world.size:
        raise ValueError(
            f"batch_size {config.batch_size} must divide among the {world.size} processes"
        )
    device = torch.device(world.device)
    clip_names, heldout, contents = None, None, None
    if features is None:
        loaded = _load_data(config)
        contents = loaded["contents"]
        features, clip_names, heldout = loaded["features"], loaded["clip_names"], loaded["heldout"]
        normalizer, skeleton, layout = loaded["normalizer"], loaded["skeleton"], loaded["layout"]
    windows = make_windows(features, config.rollout).to(device)  # (W, N_r + 1, D)
    weights = None  # None: uniform over windows
    if config.locomotion_share is not None:
        if contents is None:
            raise InputError("locomotion_share needs the corpus's content labels, not features")
        lengths = [len(f) for f in features]
        weights = window_weights(lengths, config.rollout, contents, config.locomotion_share)
        weights = weights.to(device)
    clip_x0 = resolve_clip_x0(config.clip_x0, features)  # 'data': the frames' range
    x_dim = windows.shape[-1]
    schedule = NoiseSchedule(config.schedule, config.T, device=device)

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = build_network(config, x_dim).to(device)
    ema = copy.deepcopy(model).eval() if config.ema_decay > 0 else None
    for p in ema.parameters() if ema is not None else ():
        p.requires_grad_(False)
    params = list(model.parameters())
    # DDP averages the gradients over the processes during backward (minimdm.distributed)
    trained = model if world.size == 1 else DistributedDataParallel(model)
    opt = torch.optim.Adam(params, lr=config.lr)
    gen = torch.Generator(device=device).manual_seed(config.seed)
    paths = checkpoint_paths(out_dir)
    step, prior_seconds = 0, 0.0  # prior_seconds: training time of the runs this one resumes
    segments: list[dict] = []  # the earlier calls that trained this run (model.json "segments")
    if resume:
        step, prior_seconds = resume_training(
            out_dir, asdict(config), model, opt, gen, ema, resumable=_RESUMABLE_CHANGES
        )
        if step:
            segments = list(load_train_state(out_dir)[0].get("segments", []))
    segment = {
        "command": (metadata or {}).get("command"),
        "host": platform.node(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "threads": torch.get_num_threads(),
        "device": str(device),
        "from_step": step,
    }
    if world.size > 1:  # each process draws its own batches: a generator per rank and start
        gen.manual_seed(config.seed + 7919 * world.rank + 104729 * step)

    metadata_base = {
        **(metadata or {}),
        "config": asdict(config),
        "config_file": config.config_file,
        "feature_layout": layout,
        "skeleton": skeleton,
        "normalizer": normalizer,
        "ema": ema is not None,
        "data": {
            "corpus": config.corpus,
            "split": config.split,
            "clips": clip_names,
            "fps": config.fps,
            "windows": int(windows.shape[0]),
        },
    }
    if config.model_kind == "amdm":
        metadata_base["diffusion"] = {
            "schedule": config.schedule,
            "T": config.T,
            "predicts": config.predicts,
            "clip_x0": clip_x0,
        }

    def save(at_step: int) -> None:
        if not world.is_main:
            return
        state = {
            "step": at_step,
            "model": model.state_dict(),
            "ema": ema.state_dict() if ema is not None else None,
            "optimizer": opt.state_dict(),
            "generator": gen.get_state(),
        }
        seconds = prior_seconds + time.perf_counter() - t0  # wall time of the loop, all runs
        this = {**segment, "to_step": at_step, "seconds": round(time.perf_counter() - t0, 1)}
        meta = dict(metadata_base, step=at_step, train_seconds=round(seconds, 1))
        meta["segments"] = [*segments, this]  # one per call: a run may span sessions
        save_checkpoint(
            out_dir,
            ema if ema is not None else model,
            meta,
            optimizer_state=state,
            storage=config.storage,
        )

    loss_kw = dict(
        kind=config.model_kind,
        schedule=schedule,
        predicts=config.predicts,
        kl_beta=config.kl_beta,
        clip_x0=clip_x0,
    )
    loss_kw["norm"] = config.norm
    train_kw = dict(
        loss_kw,
        teacher_weight=config.teacher_weight,
        student_steps=config.student_steps,
        snr_gamma=config.snr_gamma,
        snr_floor=config.snr_floor,
        geometry=_geometry(config, windows, normalizer, skeleton),
    )

    # Built-in evaluation: teacher-forced loss on fixed windows with its own generator, on the
    # training takes (eval_loss) and, when the config trains on a split, the test takes.
    eval_gen = torch.Generator(device=device)
    eval_idx = torch.randperm(windows.shape[0], generator=torch.Generator().manual_seed(1234))
    eval_windows = windows[eval_idx[: config.eval_windows].to(device)]
    heldout_windows = None
    if heldout:  # the same number of windows from the held-out takes
        hw = make_windows(heldout, config.rollout).to(device)
        h_idx = torch.randperm(hw.shape[0], generator=torch.Generator().manual_seed(1234))
        heldout_windows = hw[h_idx[: config.eval_windows].to(device)]

    def evaluate(at_step: int) -> dict[str, float]:
        net = ema if ema is not None else model
        net.eval()
        eval_gen.manual_seed(config.seed + 1)
        with torch.no_grad():
            loss, _ = window_loss(net, eval_windows, 0.0, eval_gen, **loss_kw)
            out = {"eval_loss": float(loss)}
            if heldout_windows is not None:
                eval_gen.manual_seed(config.seed + 1)
                loss, _ = window_loss(net, heldout_windows, 0.0, eval_gen, **loss_kw)
                out["heldout_loss"] = float(loss)
        if eval_fn is not None:
            out.update(eval_fn(net, at_step))
        model.train()
        return out

    log_path = out_dir / "log.jsonl"
    out_dir.mkdir(parents=True, exist_ok=True)
    if log_path.exists() and world.is_main:  # drop records past the resumed step
        keep = [ln for ln, rec in read_log(log_path) if rec["step"] <= step]
        atomic_write(log_path, "".join(ln + "\n" for ln in keep))
    history: list[dict] = []

    def log(record: dict) -> None:
        history.append(record)
        if not world.is_main:
            return
        with open(log_path, "a") as f:
            f.write(json.dumps(record) + "\n")

    model.train()
    start_step = step
    t0 = time.perf_counter()
    with tqdm(
        total=config.total_steps,
        initial=step,
        disable=not progress or not world.is_main,
        desc=config.model_kind,
    ) as bar:
        running, n_running = 0.0, 0
        while step < config.total_steps:
            lr = learning_rate(config, step)
            set_lr(opt, lr)
            p = student_probability(config, step)
            B, W = config.batch_size // world.size, windows.shape[0]  # this process's share
            if weights is None:
                idx = torch.randint(W, (B,), generator=gen, device=device)
            else:
                idx = torch.multinomial(weights, B, replacement=True, generator=gen)
            loss, info = window_loss(trained, windows[idx], p, gen, **train_kw)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"training loss became {loss.item()} at step {step}")
            optimizer_step(opt, loss, params, config.grad_clip)
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
    if world.size > 1:
        torch.distributed.barrier()  # rank 0's checkpoint is on disk before anyone loads it
    distributed.teardown(world)
    done = step - start_step
    return TrainResult(
        checkpoint=load_checkpoint(out_dir, device=device),
        steps=step,
        seconds=seconds,
        steps_per_second=done / seconds if seconds > 0 and done else 0.0,
        history=history,
    )


def _geometry(config: TrainConfig, windows: Tensor, normalizer: Any, skeleton: Any):
    """The geometric losses of ``config`` (None when all their weights are 0): the normalizer's
    statistics, the skeleton's feet, and the feet's contact height read off the training frames
    as the foot-sliding metric reads it (:func:`~minimdm.motion.metrics.foot_contact_offsets`)."""
    if config.model_kind != "amdm" or not (
        config.geo_consistency or config.geo_contact or config.geo_bones
    ):
        return None
    if normalizer is None or skeleton is None:
        raise InputError("geometric losses need the normalizer and the skeleton of the data")
    from minimdm.motion.features import Normalizer
    from minimdm.motion.metrics import foot_contact_offsets
    from minimdm.motion.skeleton import Skeleton

    norm = normalizer if isinstance(normalizer, Normalizer) else Normalizer.from_dict(normalizer)
    sk = skeleton if isinstance(skeleton, Skeleton) else Skeleton.from_dict(skeleton)
    J = len(sk)
    frames = norm.denormalize(windows[:, 0].cpu())  # (W, D)
    pos = frames[:, 3 : 3 + 3 * J].unflatten(-1, (J, 3)).double()
    offset = foot_contact_offsets(pos, sk.foot_indices)
    return FrameGeometry(
        norm.mean.to(windows.device),
        norm.std.to(windows.device),
        J,
        sk.foot_indices,
        offset,
        consistency=config.geo_consistency,
        contact=config.geo_contact,
        parents=sk.parents,
        bones=config.geo_bones,
    )


# --------------------------------------------------------------------------------------------
# The x0 clamp: the training data's range


def read_log(path: str | os.PathLike) -> list[tuple[str, dict]]:
    """The records of a training log (``log.jsonl``), each with its line of text.

    A process killed while appending leaves a torn last line: it is skipped with a warning that
    names the file (the training state, written atomically, is intact). A bad line elsewhere is
    no kill's doing and raises a ``ValueError`` naming the file and the line.
    """
    path = Path(path)
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    out = []
    for i, ln in enumerate(lines, start=1):
        try:
            rec = json.loads(ln)
            if not isinstance(rec, dict) or not isinstance(rec.get("step"), int):
                raise ValueError("a record must be a JSON object with an integer 'step'")
        except ValueError as e:
            if i == len(lines):
                warnings.warn(
                    f"{path}:{i}: skipping a torn last log line (a run killed while writing "
                    f"it?): {ln[:60]!r}",
                    stacklevel=2,
                )
                break
            raise ValueError(
                f"{path}:{i}: expected a JSON log record with a 'step', got {ln[:60]!r} ({e}); "
                "fix or delete that line to resume"
            ) from None
        out.append((ln, rec))
    return out


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
    from minimdm.motion import features

    cfg, meta = ckpt.config, ckpt.metadata
    names = (meta.get("data") or {}).get("clips") or cfg.get("clips")
    corpus, split = cfg.get("corpus", "deepmimic"), cfg.get("split")
    clips = _load_clips(corpus, split, cfg.get("fps", 30.0), names, cfg.get("loop_frames", 150))
    if ckpt.normalizer is None:
        raise ValueError(f"checkpoint {ckpt.paths.weights} records no normalizer")
    norm = features.Normalizer.from_dict(ckpt.normalizer)
    clips = _with_mirrored(clips, bool(cfg.get("mirror", False)))
    return torch.cat([norm.normalize(features.encode(c)) for c in clips])  # (N, D)


def checkpoint_clamp_share(
    ckpt: Checkpoint, clip_x0: Any = "checkpoint", frames: Tensor | None = None
) -> float:
    """The share of a checkpoint's training frames that its x0 clamp would change.

    ``clip_x0="checkpoint"`` takes the checkpoint's ``diffusion.clip_x0``; pass another value
    (e.g. 5.0, or a per-feature range) to compare. ``frames`` default to
    :func:`checkpoint_training_frames`. A frame outside the clamp cannot come out of the sampler
    unchanged: 0 for the training range (``clip_x0: data``), more for a tighter box, which in
    exchange keeps rollouts on the data (chapter 3).
    """
    if clip_x0 == "checkpoint":
        clip_x0 = (ckpt.metadata.get("diffusion") or {}).get("clip_x0")
    frames = checkpoint_training_frames(ckpt) if frames is None else frames
    return clamp_share(clip_x0, frames)
