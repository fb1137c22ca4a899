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
:mod:`minimdm.amdm.losses`; the loop (resume, EMA, log, checkpoints) is the one of
:mod:`minimdm.training`, shared with CAMDM; this module holds what is A-MDM's own: the data, the
batches and their loss, the evaluation and the checkpoint's metadata.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel

from minimdm import distributed
from minimdm.amdm.losses import FrameGeometry, make_windows, window_loss
from minimdm.amdm.train_config import (
    TrainConfig,
    build_network,
    delta_scale,
    learning_rate,
    load_config,
    motion_mask,
    root_mask,
    student_probability,
)
from minimdm.checkpoint import Checkpoint, load_checkpoint
from minimdm.diffusion import (
    NoiseSchedule,
    clamp_share,
    clip_bounds,
    data_range,
)
from minimdm.files import RunLock
from minimdm.motion.corpora import LOCOMOTION
from minimdm.motion.data import MotionDataset
from minimdm.training import Recipe, StepOut, TrainState, read_log, start_training, train_loop
from minimdm.utils import num_threads as threads
from minimdm.validate import (
    InputError,
    InputTypeError,
    MismatchError,
    check_output_dir,
    describe,
)

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
    if config.extra_corpus is not None:
        extra = _extra_clips(config, clips[0].skeleton)
        twice = sorted(set(clips.names) & {c.name for c in extra})
        if twice:
            raise InputError(f"takes {twice[:3]} are in both {config.corpus} and extra_corpus")
        clips = MotionDataset(list(clips) + extra)
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
    lengths: Sequence[int],
    n: int,
    contents: Sequence[str | None],
    share: float,
    split: str = "equal",
) -> Tensor:
    """Sampling weights (W,) of the windows :func:`make_windows` cuts from clips of these
    lengths (F_i - n windows each): locomotion windows get ``share`` in all, split equally
    among the locomotion contents present (``split="equal"``) or by count (``"frames"``); the
    others get ``1 - share`` by count. The weights sum to 1. With no clip of either kind, the
    other kind gets everything."""
    if split not in ("equal", "frames"):
        raise ValueError(f"split must be 'equal' or 'frames', got {split!r}")
    if len(lengths) != len(contents):
        raise ValueError(f"{len(lengths)} clips but {len(contents)} content labels")
    counts = [max(0, int(f) - n) for f in lengths]
    loco = sorted({c for c, k in zip(contents, counts, strict=True) if c in LOCOMOTION and k})
    other = sum(k for c, k in zip(contents, counts, strict=True) if c not in LOCOMOTION)
    if not loco or not other:
        share = 1.0 if loco else 0.0
    per_content = {c: sum(k for d, k in zip(contents, counts, strict=True) if d == c) for c in loco}
    moving = sum(per_content.values())
    parts = []
    for c, k in zip(contents, counts, strict=True):
        if not k:
            continue
        if c not in LOCOMOTION:
            w = (1 - share) / other
        elif split == "equal":
            w = share / len(loco) / per_content[c]
        else:
            w = share / moving
        parts.append(torch.full((k,), w, dtype=torch.float64))
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)


def _with_mirrored(clips: Any, mirror: bool) -> list:
    """The clips, followed by their mirror images when ``mirror`` (:mod:`minimdm.motion.mirror`)."""
    from minimdm.motion.mirror import mirror_clips

    clips = list(clips)
    return clips + mirror_clips(clips) if mirror else clips


def _extra_clips(config: TrainConfig, skeleton: Any) -> list:
    """The takes of ``config.extra_corpus`` (a corpus name or a folder of BVH files; of
    ``extra_contents`` only, when given), checked to share the corpus's skeleton: the same joints
    in the same order."""
    from minimdm.motion.corpora import load_motion

    extra = load_motion(config.extra_corpus, fps=config.fps)
    if config.extra_contents is not None:
        have = {c.labels.get("content") for c in extra}
        unknown = sorted(set(config.extra_contents) - have)
        if unknown:
            raise InputError(
                f"extra_contents {unknown} are not contents of {config.extra_corpus!r}; "
                f"it has {sorted(h for h in have if h)}"
            )
        extra = [c for c in extra if c.labels.get("content") in set(config.extra_contents)]
    for clip in extra:
        theirs = (list(clip.skeleton.names), list(clip.skeleton.parents))
        if theirs != (list(skeleton.names), list(skeleton.parents)):
            raise MismatchError(
                f"{config.extra_corpus} take {clip.name} has joints {theirs[0]} (parents "
                f"{theirs[1]}); {config.corpus} has {list(skeleton.names)} (parents "
                f"{list(skeleton.parents)})"
            )
    return list(extra)


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
    """The A-MDM parts (data, batches, losses, evaluation, metadata) on the shared loop."""
    out_dir = Path(out_dir)
    world = distributed.setup(config.device)  # one process, or one of torchrun's N
    if config.batch_size % world.size:
        raise ValueError(
            f"batch_size {config.batch_size} must divide among the {world.size} processes"
        )
    device = torch.device(world.device)
    data = _Data.build(config, features, normalizer, skeleton, layout, device)
    state = start_training(
        config,
        out_dir,
        lambda: build_network(config, data.windows.shape[-1], _delta(config, data)).to(device),
        torch.Generator(device=device),
        resume=resume,
        resumable=_RESUMABLE_CHANGES,
    )
    if world.size > 1:  # each process draws its own batches: a generator per rank and start
        state.generator.manual_seed(config.seed + 7919 * world.rank + 104729 * state.step)
    recipe = Recipe(
        name=config.model_kind,
        learning_rate=lambda step: learning_rate(config, step),
        batch_loss=_batch_loss(config, data, state, world),
        evaluate=_evaluator(config, data, eval_fn),
        metadata=_metadata(config, data, metadata),
        device=str(device),
        storage=config.storage,
    )
    run = train_loop(
        config, out_dir, state, recipe, progress=progress, callback=callback, is_main=world.is_main
    )
    if world.size > 1:
        torch.distributed.barrier()  # rank 0's checkpoint is on disk before anyone loads it
    distributed.teardown(world)
    done = run.step - run.start_step
    return TrainResult(
        checkpoint=load_checkpoint(out_dir, device=device),
        steps=run.step,
        seconds=run.seconds,
        steps_per_second=done / run.seconds if run.seconds > 0 and done else 0.0,
        history=run.history,
    )


@dataclass
class _Data:
    """The training windows of a run and what its losses and checkpoint need to know of them."""

    windows: Tensor
    """(W, H - 1 + N_r + 1, D): every window of consecutive normalized frames, the H - 1
    more of a model with a history of H frames first."""
    weights: Tensor | None
    """(W,) sampling weights of the windows (None: uniform)."""
    heldout: Tensor | None
    """The held-out takes' windows, or None."""
    clip_x0: Any
    """The config's ``clip_x0`` made concrete (:func:`resolve_clip_x0`)."""
    normalizer: Any
    skeleton: Any
    layout: Any
    clip_names: list[str] | None

    @classmethod
    def build(
        cls,
        config: TrainConfig,
        features: Sequence[Tensor | np.ndarray] | None,
        normalizer: Any,
        skeleton: Any,
        layout: Any,
        device: torch.device,
    ) -> _Data:
        """The config's clips (``features`` None) or the given in-memory features, windowed."""
        clip_names, heldout, contents = None, None, None
        if features is None:
            loaded = _load_data(config)
            contents, clip_names = loaded["contents"], loaded["clip_names"]
            features, heldout = loaded["features"], loaded["heldout"]
            normalizer, skeleton, layout = (loaded[k] for k in ("normalizer", "skeleton", "layout"))
        n = config.rollout + config.history - 1  # frames after a window's first
        windows = make_windows(features, n).to(device)  # (W, n + 1, D)
        weights = None  # None: uniform over windows
        if config.locomotion_share is not None:
            if contents is None:
                raise InputError("locomotion_share needs the corpus's content labels, not features")
            lengths = [len(f) for f in features]
            weights = window_weights(
                lengths, n, contents, config.locomotion_share, config.locomotion_split
            )
            weights = weights.to(device)
        heldout_windows = None
        if heldout:
            heldout_windows = make_windows(heldout, n).to(device)
        clip_x0 = resolve_clip_x0(config.clip_x0, features)  # 'data': the frames' range
        return cls(
            windows, weights, heldout_windows, clip_x0, normalizer, skeleton, layout, clip_names
        )


def _delta(config: TrainConfig, data: _Data) -> list[float] | None:
    """A delta model's scale k, from the training windows (None for other models)."""
    return delta_scale(data.windows) if config.delta else None


def _loss_kw(config: TrainConfig, data: _Data, device: torch.device) -> dict[str, Any]:
    """The keyword arguments of :func:`window_loss` shared by training and evaluation."""
    return dict(
        kind=config.model_kind,
        schedule=NoiseSchedule(config.schedule, config.T, device=device),
        predicts=config.predicts,
        kl_beta=config.kl_beta,
        clip_x0=data.clip_x0,
        norm=config.norm,
        history=config.history,
    )


def _cond_spread(config: TrainConfig, model: nn.Module) -> float | torch.Tensor:
    """The spread of the condition noise: ``cond_noise`` as a float (the loss reads it in a
    delta model's units of change), or with ``cond_noise_motion`` each feature's spread (D,) in
    normalized frame units, the two noises independent."""
    if config.cond_noise_motion <= 0 and config.cond_noise_root == 1:
        return config.cond_noise
    net = getattr(model, "module", model)
    x_dim = net.config.x_dim
    base = torch.full((x_dim,), float(config.cond_noise))
    if net.is_delta:
        base = net.delta_spread.cpu() * config.cond_noise
    motion = torch.tensor(motion_mask(x_dim)) * config.cond_noise_motion
    root = torch.tensor(root_mask(x_dim))  # the pace, scaled by cond_noise_root
    factor = 1 - root * (1 - config.cond_noise_root)
    return ((base**2 + motion**2).sqrt() * factor).to(net.delta_spread.device)


def _batch_loss(
    config: TrainConfig, data: _Data, state: TrainState, world: distributed.World
) -> Callable[[int], StepOut]:
    """A batch of windows drawn by the run's generator and its scheduled-sampling loss."""
    windows, weights, gen = data.windows, data.weights, state.generator
    # DDP averages the gradients over the processes during backward (minimdm.distributed)
    trained = state.model if world.size == 1 else DistributedDataParallel(state.model)
    train_kw = dict(
        _loss_kw(config, data, windows.device),
        teacher_weight=config.teacher_weight,
        student_steps=config.student_steps,
        snr_gamma=config.snr_gamma,
        snr_floor=config.snr_floor,
        cond_noise=_cond_spread(config, state.model),
        cond_noise_draw=config.cond_noise_draw,
        cond_noise_history=config.cond_noise_history,
        delta_from=config.delta_from,
        geometry=_geometry(config, windows, data.normalizer, data.skeleton),
    )

    def batch_loss(step: int) -> StepOut:
        p = student_probability(config, step)
        B, W = config.batch_size // world.size, windows.shape[0]  # this process's share
        if weights is None:
            idx = torch.randint(W, (B,), generator=gen, device=windows.device)
        else:
            idx = torch.multinomial(weights, B, replacement=True, generator=gen)
        loss, info = window_loss(trained, windows[idx], p, gen, **train_kw)
        return StepOut(loss, status={"p_student": p}, extra=info)

    return batch_loss


def _evaluator(
    config: TrainConfig,
    data: _Data,
    eval_fn: Callable[[nn.Module, int], dict[str, float]] | None,
) -> Callable[[nn.Module, int], dict[str, float]]:
    """Built-in evaluation: the teacher-forced loss on fixed windows with its own generator, on
    the training takes (``eval_loss``) and, when the config trains on a split, the test takes
    (``heldout_loss``); then ``eval_fn``'s metrics."""
    device = data.windows.device
    loss_kw = _loss_kw(config, data, device)
    eval_gen = torch.Generator(device=device)
    sets = {"eval_loss": data.windows}
    if data.heldout is not None:  # the same number of windows from the held-out takes
        sets["heldout_loss"] = data.heldout
    for name, w in sets.items():
        idx = torch.randperm(w.shape[0], generator=torch.Generator().manual_seed(1234))
        sets[name] = w[idx[: config.eval_windows].to(device)]

    def evaluate(net: nn.Module, step: int) -> dict[str, float]:
        net.eval()
        out = {}
        with torch.no_grad():
            for name, windows in sets.items():
                eval_gen.manual_seed(config.seed + 1)
                loss, _ = window_loss(net, windows, 0.0, eval_gen, **loss_kw)
                out[name] = float(loss)
        if eval_fn is not None:
            out.update(eval_fn(net, step))
        return out

    return evaluate


def _metadata(config: TrainConfig, data: _Data, metadata: dict[str, Any] | None) -> dict:
    """What an A-MDM checkpoint records besides the config: data, layout, normalizer..."""
    meta = {
        **(metadata or {}),
        "feature_layout": data.layout,
        "skeleton": data.skeleton,
        "normalizer": data.normalizer,
        "data": {
            "corpus": config.corpus,
            "split": config.split,
            "clips": data.clip_names,
            "fps": config.fps,
            "windows": int(data.windows.shape[0]),
        },
    }
    if config.model_kind == "amdm":
        meta["diffusion"] = {
            "schedule": config.schedule,
            "T": config.T,
            "predicts": config.predicts,
            "clip_x0": data.clip_x0,
        }
    return meta


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
    from minimdm.amdm.evaluation import checkpoint_clips
    from minimdm.motion import features

    if ckpt.normalizer is None:
        raise ValueError(f"checkpoint {ckpt.paths.weights} records no normalizer")
    norm = features.Normalizer.from_dict(ckpt.normalizer)
    clips = _with_mirrored(checkpoint_clips(ckpt), bool(ckpt.config.get("mirror", False)))
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
        clip_x0 = ckpt.diffusion.get("clip_x0")
    frames = checkpoint_training_frames(ckpt) if frames is None else frames
    return clamp_share(clip_x0, frames)
