"""The evaluation protocol of A-MDM §7.3 on the DeepMimic clips: Tables 1-4 and drift.

* **Table 1, random sampling.** ``n_states`` fixed initial states drawn uniformly from the
  training clips (a fixed seed picks them); from each, ``n_samples`` futures of ``apd_frames``
  frames. APD over all of them, ADE/FDE over their first ``ade_frames`` frames against the
  ground-truth continuation of that state; foot sliding, bone error, joint acceleration and
  foot penetration over all frames. Each metric is averaged over the states; the whole is
  repeated for every seed and reported as mean ± std (:func:`evaluate`).
* **Table 2, motion continuation.** The initial states are taken from the last 30 frames of
  every clip as recorded (loops not unrolled), so the models must go on past the end of the
  data; there is no ground truth, so no ADE (:func:`continuation_states`).
* **Tables 3/4, denoising steps.** Models trained with different T, APD, ADE, FS and the
  ms/frame of sampling measured in the same run (:func:`time_per_frame`).
* **Drift.** Bone error and root height over a long rollout, per window (:func:`drift`).

The dataset's own row (:func:`dataset_row`) gives the targets for Jnt.Accel (closer is better)
and the floor of FS and penetration that the measurement itself produces. Rows print with
:func:`format_table` (:func:`minimdm.utils.format_table`); the chapter's steps sweep and its
stored benchmark rows are :mod:`minimdm.studies.amdm_tables`.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from minimdm.amdm.sampling import history_of, rollout
from minimdm.checkpoint import DEFAULT_FPS, Checkpoint
from minimdm.motion import metrics
from minimdm.motion.corpora import load_motion
from minimdm.motion.data import MotionDataset
from minimdm.motion.features import FeatureLayout, StartPose, encode, start_pose_of
from minimdm.motion.skeleton import Skeleton
from minimdm.utils import format_table  # re-exported: the chapters print tables with it
from minimdm.validate import InputError, check_int

__all__ = [
    "Protocol",
    "InitialState",
    "checkpoint_skeleton",
    "checkpoint_clips",
    "initial_state",
    "random_states",
    "available_states",
    "continuation_states",
    "evaluate",
    "dataset_row",
    "table1",
    "table2",
    "time_per_frame",
    "drift",
    "pose_distance_to_training",
    "memorisation_probe",
    "format_table",
]

TABLE1_COLUMNS = ("APD", "ADE", "FDE", "FS", "Bone.Err", "Jnt.Accel", "Pen.Freq", "Pen.Dist")
TABLE2_COLUMNS = ("APD", "FS", "Bone.Err", "Jnt.Accel", "Pen.Freq", "Pen.Dist")


def _in_table_order(names) -> list[str]:
    """Metric names in the order of Table 1, then any others sorted (rows print in this order)."""
    return [c for c in TABLE1_COLUMNS if c in names] + sorted(set(names) - set(TABLE1_COLUMNS))


@dataclass
class Protocol:
    """How many states, samples, frames and seeds an evaluation uses (A-MDM §7.3)."""

    n_states: int = 10
    """Fixed initial states (drawn once with ``state_seed``)."""
    n_samples: int = 50
    """Futures per initial state (the paper: 50)."""
    apd_frames: int = 150
    """Frames per sample for APD and the quality metrics (the paper: 150)."""
    ade_frames: int = 60
    """Frames compared with the ground truth for ADE/FDE (the paper: 60)."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Sampling seeds; metrics are reported as mean ± std over them."""
    state_seed: int = 0
    """Seed that picks the initial states."""
    split: str | None = "test"
    """Where the initial states come from: 'test' (the held-out takes of a checkpoint trained on
    a corpus's 'train' split, as the paper evaluates) or None (the training clips). A checkpoint
    trained without a split always starts from its training clips."""

    def __post_init__(self) -> None:
        for name in ("n_states", "n_samples", "apd_frames", "ade_frames"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.n_samples < 2:
            raise ValueError(f"n_samples must be >= 2 for APD, got {self.n_samples}")
        if self.ade_frames > self.apd_frames:
            raise ValueError(
                f"ade_frames ({self.ade_frames}) must be <= apd_frames ({self.apd_frames})"
            )
        self.seeds = tuple(int(s) for s in self.seeds)
        if not self.seeds:
            raise ValueError("seeds must hold at least one seed")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class InitialState:
    """One initial state x_0 and where it came from."""

    clip: str
    """Name of the source clip."""
    frame: int
    """Index of the clip frame that x_0 describes."""
    features: Tensor
    """(D,) x_0 in feature units (``features.encode``)."""
    start_pose: StartPose
    """Root ground position and heading at that frame (decoding starts there)."""
    reference: np.ndarray | None = field(default=None, repr=False)
    """(F_ref, J, 3) ground-truth positions of the frames after it, or None."""
    bone_lengths: np.ndarray | None = field(default=None, repr=False)
    """(J - 1,) the clip's own bone lengths (actors differ), the reference of Bone.Err."""
    past: Tensor | None = field(default=None, repr=False)
    """(P, D) the feature rows that end with x_0 (up to :data:`PAST_FRAMES` of them), for a
    model that conditions on several frames; None: x_0 alone."""

    def condition(self, history: int) -> Tensor:
        """x_0 (D,) for ``history`` 1, else the ``history`` frames (H, D) that end with it. A
        state nearer the clip's start than that repeats the clip's first frame before it."""
        if history == 1:
            return self.features
        past = self.past if self.past is not None else self.features[None]
        if history > len(past):
            past = torch.cat([past[:1].expand(history - len(past), -1), past])
        return past[-history:]


PAST_FRAMES = 30
"""How many frames an :class:`InitialState` keeps before and with x_0."""


def checkpoint_skeleton(ckpt: Checkpoint) -> Skeleton:
    """The skeleton a checkpoint was trained on (stored in its metadata)."""
    if ckpt.skeleton is None:
        raise ValueError(f"checkpoint {ckpt.paths.weights} records no skeleton")
    return Skeleton.from_dict(ckpt.skeleton)


def checkpoint_clips(
    ckpt: Checkpoint | None = None, unrolled: bool = True, split: str = "train"
) -> MotionDataset:
    """The clips a checkpoint was trained on, as it saw them (fps, loop unrolling; with its
    ``extra_corpus``'s takes too), or its corpus's held-out takes.

    Args:
        ckpt: the checkpoint (None: the 20 DeepMimic clips).
        unrolled: unroll looping clips as training did (DeepMimic only).
        split: ``"train"`` (the clips it learnt from) or ``"test"`` (the test takes of the
            corpus's fixed split; only for a checkpoint trained on its ``"train"`` split).

    The datasets are loaded once per process and shared: treat them as read-only.
    """
    cfg = ckpt.config if ckpt is not None else {}
    data = ckpt.metadata.get("data", {}) if ckpt is not None else {}
    corpus, trained_on = cfg.get("corpus", "deepmimic"), cfg.get("split")
    loop = cfg.get("loop_frames", 150) if unrolled else None
    fps = ckpt.fps if ckpt is not None else DEFAULT_FPS
    if split == "train":
        names = data.get("clips") or cfg.get("clips")
        if cfg.get("extra_corpus") and names:  # two sources: each clip from its own
            own = _motion(corpus, trained_on, fps, None, loop)
            rest = tuple(n for n in names if n not in set(own.names))
            extra = _motion(cfg["extra_corpus"], None, fps, rest, loop) if rest else []
            both = {c.name: c for c in [*own, *extra]}
            return MotionDataset([both[n] for n in names])
        return _motion(corpus, trained_on, fps, tuple(names) if names else None, loop)
    if split != "test":
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    if trained_on != "train":
        raise ValueError(
            f"checkpoint was trained on {corpus!r} with split {trained_on!r}: it has no "
            "held-out takes (train on split: train to keep the test takes out)"
        )
    return _motion(corpus, "test", fps, None, loop)


@functools.lru_cache(maxsize=8)
def _motion(corpus: str, split: Any, fps: float, names: Any, loop: Any) -> MotionDataset:
    """:func:`load_motion`, remembered: the protocol asks for the same clips many times (a
    corpus takes seconds to load). The clips are shared, so callers must not change them."""
    return load_motion(corpus, split, fps, list(names) if names else None, loop)


def _start_clips(ckpt: Checkpoint, protocol: Protocol, unrolled: bool = True) -> MotionDataset:
    """The clips a protocol's initial states come from (:attr:`Protocol.split`)."""
    held_out = protocol.split == "test" and ckpt.config.get("split") == "train"
    return checkpoint_clips(ckpt, unrolled, "test" if held_out else "train")


def _state(clip, feats: Tensor, frame: int, ref_frames: int) -> InitialState:
    """The state describing clip frame ``frame`` (feature row ``frame - 1``)."""
    if not 1 <= frame < clip.n_frames:
        raise InputError(
            f"frame must lie in [1, {clip.n_frames - 1}] for clip {clip.name!r}, got {frame}"
        )
    sp = start_pose_of(clip, frame)
    ref = clip.positions[frame + 1 : frame + 1 + ref_frames] if ref_frames else None
    sk = clip.skeleton
    bones = metrics.skeleton_bone_lengths(sk.offsets, sk.parents)
    past = feats[max(0, frame - PAST_FRAMES) : frame]  # the rows that end with x_0
    return InitialState(clip.name, frame, feats[frame - 1], sp, ref, bones, past)


def initial_state(
    ckpt: Checkpoint | None, clip: str, frame: int = 0, ref_frames: int = 0
) -> InitialState:
    """The initial state at ``frame`` of ``clip`` (frame 0 is taken as frame 1: it has no
    velocity), with ``ref_frames`` frames of ground truth after it when the clip has them.

    ``clip`` names a training clip or, for a checkpoint trained on a corpus's training split,
    a held-out test take."""
    frame = check_int("frame", frame, low=0)
    ref_frames = check_int("ref_frames", ref_frames, low=0)
    dataset = checkpoint_clips(ckpt)
    names = list(dataset.names)
    if clip not in dataset.names and ckpt is not None and ckpt.config.get("split") == "train":
        dataset = checkpoint_clips(ckpt, split="test")
        names += dataset.names
    if clip not in dataset.names:
        shown = ", ".join(names[:6]) + (f", ... ({len(names)} in all)" if len(names) > 6 else "")
        raise InputError(
            f"clip must name a clip of the checkpoint's motion ({shown}), got {clip!r}"
        )
    c = dataset[clip]
    return _state(c, encode(c), max(1, frame), ref_frames)


def _state_pool(dataset: MotionDataset, ref_frames: int) -> list[tuple[Any, int]]:
    """Every (clip, frame) that can start an evaluation: ``ref_frames`` frames follow it."""
    return [(c, f) for c in dataset for f in range(1, c.n_frames - ref_frames)]


def available_states(ckpt: Checkpoint, protocol: Protocol | None = None) -> int:
    """How many initial states :func:`table1` can draw for ``ckpt`` (its ``n_states`` limit)."""
    protocol = protocol or Protocol()
    return len(_state_pool(_start_clips(ckpt, protocol), protocol.ade_frames))


def random_states(
    dataset: MotionDataset, n: int, ref_frames: int = 60, seed: int = 0
) -> list[InitialState]:
    """``n`` initial states drawn uniformly over every frame that has ``ref_frames`` after it."""
    feats = {c.name: encode(c) for c in dataset}
    pool = _state_pool(dataset, ref_frames)
    if len(pool) < n:
        raise ValueError(f"n must be <= {len(pool)} (frames with {ref_frames} after them), got {n}")
    pick = np.random.default_rng(seed).choice(len(pool), size=n, replace=False)
    return [_state(pool[i][0], feats[pool[i][0].name], pool[i][1], ref_frames) for i in pick]


def continuation_states(
    dataset: MotionDataset, per_clip: int = 1, last: int = 30, seed: int = 0
) -> list[InitialState]:
    """Table 2: ``per_clip`` states from the last ``last`` frames of every clip (no reference)."""
    rng = np.random.default_rng(seed)
    out = []
    for c in dataset:
        lo = max(1, c.n_frames - last)
        frames = rng.choice(np.arange(lo, c.n_frames), size=min(per_clip, c.n_frames - lo))
        feats = encode(c)
        out += [_state(c, feats, int(f), 0) for f in sorted(frames)]
    return out


def _conditions(ckpt: Checkpoint, states: Sequence[InitialState]) -> Tensor:
    """The start of a rollout from each state: x_0 (C, D), or the H frames that end with it
    (C, H, D) for a model that conditions on H (:attr:`InitialState.condition`)."""
    history = history_of(ckpt.model)
    return torch.stack([s.condition(history) for s in states])


def _stack_start(states: Sequence[InitialState]) -> StartPose:
    xy = torch.stack([torch.as_tensor(s.start_pose.xy, dtype=torch.float64) for s in states])
    h = torch.stack([torch.as_tensor(s.start_pose.heading, dtype=torch.float64) for s in states])
    return StartPose(xy, h)


def _foot_offset(dataset: MotionDataset, skeleton: Skeleton) -> list[float]:
    pos = np.concatenate([c.positions for c in dataset])  # (sum F, J, 3)
    return metrics.foot_contact_offsets(pos, skeleton.foot_indices)


def evaluate(
    ckpt: Checkpoint,
    states: Sequence[InitialState],
    protocol: Protocol,
    *,
    steps: int | None = None,
    foot_offset: Sequence[float] | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, tuple[float, float]]:
    """Every metric of ``ckpt`` from ``states``: ``{name: (mean, std over seeds)}``.

    ADE/FDE are measured for states that carry a reference of at least ``ade_frames`` frames.
    """
    if not states:
        raise ValueError("states must hold at least one initial state")
    sk = checkpoint_skeleton(ckpt)
    if foot_offset is None:
        foot_offset = _foot_offset(checkpoint_clips(ckpt), sk)
    ckpt_len = metrics.skeleton_bone_lengths(sk.offsets, sk.parents)
    x0 = _conditions(ckpt, states)  # (C, D), or (C, H, D) for a history of H
    start = _stack_start(states)
    P = protocol

    def one_seed(seed: int) -> dict[str, float]:
        g = torch.Generator(device=device).manual_seed(seed)
        r = rollout(
            ckpt,
            x0,
            P.apd_frames,
            P.n_samples,
            steps=steps,
            generator=g,
            start_pose=start,
            device=device,
        )
        rows = []
        for c, s in enumerate(states):
            ref = s.reference
            has_ref = ref is not None and len(ref) >= P.ade_frames
            rows.append(
                metrics.motion_metrics(
                    r.positions[c],
                    sk.parents,
                    sk.foot_indices,
                    s.bone_lengths if s.bone_lengths is not None else ckpt_len,
                    reference=ref[: P.ade_frames] if has_ref else None,
                    ade_frames=P.ade_frames,
                    foot_offset=foot_offset,
                )
            )
        keys = _in_table_order(set().union(*(r.keys() for r in rows)))
        return {k: float(np.mean([r[k] for r in rows if k in r])) for k in keys}

    return metrics.over_seeds(one_seed, P.seeds)


def dataset_row(
    dataset: MotionDataset, skeleton: Skeleton, window: int = 150
) -> dict[str, tuple[float, float]]:
    """The data's own FS, bone error, Jnt.Accel and penetration (std over clips).

    Each clip is cut into windows of at most ``window`` frames, as the samples are; its bone
    error is measured against its own skeleton's bone lengths.
    """
    foot_offset = _foot_offset(dataset, skeleton)
    per_clip = [
        metrics.motion_metrics(  # one motion (F, J, 3): no APD, no ADE
            c.positions[:window],
            skeleton.parents,
            skeleton.foot_indices,
            metrics.skeleton_bone_lengths(c.skeleton.offsets, c.skeleton.parents),
            foot_offset=foot_offset,
        )
        for c in dataset
    ]
    return {k: metrics.mean_std(r[k] for r in per_clip) for k in per_clip[0]}


def table1(
    models: Mapping[str, Checkpoint],
    protocol: Protocol | None = None,
    *,
    steps: int | None = None,
    with_dataset: bool = False,
    device: torch.device | str = "cpu",
) -> dict[str, dict[str, tuple[float, float]]]:
    """Table 1 (random sampling) for several models from the same fixed initial states.

    The states come from the first model's held-out takes (:attr:`Protocol.split`); the
    ``dataset`` row measures those same takes."""
    protocol = protocol or Protocol()
    first = next(iter(models.values()))
    dataset = _start_clips(first, protocol)
    states = random_states(dataset, protocol.n_states, protocol.ade_frames, protocol.state_seed)
    sk = checkpoint_skeleton(first)
    offset = _foot_offset(checkpoint_clips(first), sk)
    out = {
        name: evaluate(ck, states, protocol, steps=steps, foot_offset=offset, device=device)
        for name, ck in models.items()
    }
    if with_dataset:
        out["dataset"] = dataset_row(dataset, sk, protocol.apd_frames)
    return out


def table2(
    models: Mapping[str, Checkpoint],
    protocol: Protocol | None = None,
    *,
    per_clip: int = 1,
    steps: int | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, dict[str, tuple[float, float]]]:
    """Table 2 (motion continuation): start at the last 30 frames of every recorded clip (the
    held-out takes under :attr:`Protocol.split`)."""
    protocol = protocol or Protocol()
    first = next(iter(models.values()))
    states = continuation_states(
        _start_clips(first, protocol, unrolled=False), per_clip, seed=protocol.state_seed
    )
    offset = _foot_offset(checkpoint_clips(first), checkpoint_skeleton(first))
    return {
        name: evaluate(ck, states, protocol, steps=steps, foot_offset=offset, device=device)
        for name, ck in models.items()
    }


@torch.no_grad()
def time_per_frame(
    ckpt: Checkpoint,
    steps: int | None = None,
    batch: int = 1,
    n_frames: int = 30,
    device: torch.device | str = "cpu",
    repeats: int = 3,
) -> float:
    """Median wall time of one generated frame, in ms, for a batch of ``batch`` characters."""
    state = initial_state(ckpt, checkpoint_clips(ckpt).names[0], 1)
    x0 = _conditions(ckpt, [state])
    x0 = x0.expand(batch, *x0.shape[1:])  # (B, D) or (B, H, D)
    g = torch.Generator(device=device).manual_seed(0)
    kw = dict(steps=steps, generator=g, decode_positions=False, device=device)
    rollout(ckpt, x0, 2, **kw)  # warm-up
    times = []
    for _ in range(repeats):
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        rollout(ckpt, x0, n_frames, **kw)
        if torch.device(device).type == "cuda":
            torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) / n_frames * 1e3)
    return float(np.median(times))


def drift(
    ckpt: Checkpoint,
    state: InitialState,
    n_frames: int = 1000,
    n_samples: int = 8,
    window: int = 100,
    seed: int = 0,
    steps: int | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, np.ndarray]:
    """Bone error (cm), root height (m) and root speed (m/s) per window of a long rollout,
    averaged over samples.

    Returns ``{"frame": (W,) window ends, "bone_err": (W,), "root_height": (W,),
    "root_height_std": (W,), "root_speed": (W,)}``: a model without scheduled sampling drifts, its
    bones stretch and its root sinks or floats; a model that converges to standing still shows it
    in the root's horizontal speed.
    """
    sk = checkpoint_skeleton(ckpt)
    ref_len = metrics.skeleton_bone_lengths(sk.offsets, sk.parents)
    g = torch.Generator(device=device).manual_seed(seed)
    r = rollout(
        ckpt,
        _conditions(ckpt, [state]),
        n_frames,
        n_samples,
        steps=steps,
        generator=g,
        start_pose=_stack_start([state]),
        device=device,
    )
    pos = r.positions[0]  # (K, F, J, 3)
    ends, bone, height, height_std, speed = [], [], [], [], []
    for a in range(0, n_frames, window):
        x = pos[:, a : a + window]
        ends.append(min(a + window, n_frames))
        bone.append(metrics.bone_length_error(x, sk.parents, ref_len))
        z = x[..., 0, 2]  # (K, w) root height
        height.append(float(z.mean()))
        height_std.append(float(z.std()))
        step = x[:, 1:, 0, :2] - x[:, :-1, 0, :2]  # (K, w - 1, 2) horizontal root steps
        speed.append(float(step.norm(dim=-1).mean()) * ckpt.fps if x.shape[1] > 1 else 0.0)
    return {
        "frame": np.array(ends),
        "bone_err": np.array(bone),
        "root_height": np.array(height),
        "root_height_std": np.array(height_std),
        "root_speed": np.array(speed),
    }


# --------------------------------------------------------------------------------------------
# Memorisation: how close generated poses come to the training poses


def _poses_cm(frames: Tensor, layout: FeatureLayout) -> Tensor:
    """(N, 3J) root-relative, heading-aligned joint positions j_p in cm, from feature rows (in
    float64: cdist's matrix-product shortcut leaves ~0.05 cm on equal poses in float32)."""
    return frames[..., layout.joint_pos].reshape(-1, 3 * layout.n_joints).double() * 100


def pose_distance_to_training(
    ckpt: Checkpoint, frames: Tensor, training: Tensor | None = None, chunk: int = 1024
) -> np.ndarray:
    """Each frame's distance to its nearest training frame, in cm.

    The distance between two poses is the root-mean-square over joints of the distance between
    their joint positions j_p (root-relative and heading-aligned, so where the character
    stands and faces does not count). A model that copies its data makes frames at distance
    ~0; real motion it never saw (the held-out takes) shows how far new poses lie.

    Args:
        ckpt: the checkpoint (its feature layout and training data).
        frames: (..., D) frames in feature units (``features.encode``, ``Rollout.features``).
        training: (N, D) the training frames in feature units (default: every frame of the
            checkpoint's training clips).
        chunk: query frames per distance matrix (memory).

    Returns:
        (M,) distances in cm, one per frame.
    """
    layout = FeatureLayout.from_dict(ckpt.metadata["feature_layout"])
    if training is None:
        training = torch.cat([encode(c) for c in checkpoint_clips(ckpt, unrolled=False)])
    bank = _poses_cm(training, layout)  # (N, 3J)
    query = _poses_cm(frames.reshape(-1, frames.shape[-1]), layout)  # (M, 3J)
    out = [
        torch.cdist(q, bank).min(dim=1).values for q in query.split(chunk)
    ]  # RMS over joints: the Euclidean norm of the 3J vector / sqrt(J)
    return (torch.cat(out) / layout.n_joints**0.5).numpy()


def memorisation_probe(
    ckpt: Checkpoint,
    protocol: Protocol | None = None,
    *,
    steps: int | None = None,
    near: float = 1.0,
    frame_stride: int = 5,
    device: torch.device | str = "cpu",
) -> dict[str, dict[str, tuple[float, float]]]:
    """Distance to the nearest training pose: generated frames next to held-out frames.

    Generated frames: every ``frame_stride``-th frame (neighbours are near-duplicates) of
    ``n_samples`` rollouts of ``apd_frames`` from each of Table 1's ``n_states`` held-out
    initial states, for every seed. Held-out frames: every frame of the
    corpus's test takes (the same for every seed). For each, the median and 90th percentile of
    :func:`pose_distance_to_training` (cm) and the share of frames nearer than ``near`` cm.
    Generated frames much nearer than held-out ones point at copying; much farther, at poses
    off the data.

    Returns:
        ``{"generated": {stat: (mean, std over seeds)}, "held-out": {stat: (value, 0.0)}}``.
    """
    protocol = protocol or Protocol()
    training = torch.cat([encode(c) for c in checkpoint_clips(ckpt, unrolled=False)])
    held_clips = _start_clips(ckpt, protocol, unrolled=False)
    states = random_states(held_clips, protocol.n_states, protocol.ade_frames, protocol.state_seed)
    x0 = _conditions(ckpt, states)  # (C, D), or (C, H, D) for a history of H

    def stats(d: np.ndarray) -> dict[str, float]:
        return {
            "median": float(np.median(d)),
            "p90": float(np.percentile(d, 90)),
            f"share<{near:g}cm": float((d < near).mean()),
        }

    def one_seed(seed: int) -> dict[str, float]:
        g = torch.Generator(device=device).manual_seed(seed)
        r = rollout(
            ckpt,
            x0,
            protocol.apd_frames,
            protocol.n_samples,
            steps=steps,
            generator=g,
            decode_positions=False,
            device=device,
        )
        frames = r.features[:, :, ::frame_stride].cpu()  # (C, K, F / stride, D)
        return stats(pose_distance_to_training(ckpt, frames, training))

    held = torch.cat([encode(c) for c in held_clips])
    held_stats = stats(pose_distance_to_training(ckpt, held, training))
    return {
        "generated": metrics.over_seeds(one_seed, protocol.seeds),
        "held-out": {k: (v, 0.0) for k, v in held_stats.items()},
    }
