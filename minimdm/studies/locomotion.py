"""Does a motion model keep moving like the data? The locomotion yardstick of chapter 3.

From frame ``start_frame`` of every held-out locomotion take of a labelled corpus (walk,
walk-back, walk-left, walk-right, run, dash), a model draws ``n_samples`` futures of
``long_seconds`` (default 60 s); the first ``seconds`` (10 s) are scored like the paper's
metrics, the whole is scored for staying power. Everything is compared with the take the
rollout started from, the recording of the same actor and content:

* **speed held**: the root's ground speed (the ``root_vel`` feature, A-MDM §3.1) over the last
  ``tail_seconds`` of the 10 s and of the 60 s, divided by the take's own mean speed. A model
  that slows to a halt scores near 0 however clean its frames are;
* **direction held**: the root velocity over the same tail, in the heading frame, projected on
  the take's own mean heading-frame velocity (a backward walk that turns into a forward walk
  keeps its speed but not this ratio);
* **still moving** after 60 s: the share of futures whose tail speed is at least
  ``moving_ratio`` of the take's;
* **foot sliding** and **joint acceleration** over the 10 s, against the same measures of the
  take itself (:mod:`minimdm.motion.metrics`), and **bone error** against the take's actor;
* **pace kept** (:func:`pace_slope`): over the six contents, the slope of the log speed after
  10 s against the log of the takes' own speed. 1: a dash stays as much faster than a backward
  walk as in the data; 0: every start ends at one pace. A mean speed ratio near 1 can hide a
  slope near 0, where the slow contents speed up as much as the fast ones slow down;
* **on locomotion** and **content kept** (:class:`ContentIndex`): over the same tails, the
  share of frames whose nearest frame among the corpus's training takes belongs to a
  locomotion take, and to a take of the start's own content, beside the same shares of the
  take's own frames. A future that leaves a walk for the corpus's gestures (arms raised,
  crouches, kicks) can keep its speed and still fail here;
* **whom it resembles** (:meth:`ContentIndex.takes`): over the same tails, the share of frames
  whose nearest training frame belongs to a take of the start's own **style** (the data's own
  frames beside it), the mean pace of those nearest takes, and the futures' speed over that
  pace. A future that slows because it has become a slower take (a sad walk, a gesture) moves
  at about the pace of the takes it resembles (near 1); one that glides at a run in a walk's
  poses scores far above 1;
* **off the data** after 10 s and 60 s: the mean distance of the tail's frames to their
  nearest training frame (every feature in its spread), over the same distance of the take's
  own frames. Near 1, the futures' poses and motions are as close to the recordings as an
  unseen take is; a future that bends over at a run or raises its arms mid-stride, poses no
  actor held, scores far above 1 even where its speed, feet and bones look right. After 10 s
  it is also given for the root's motion, the joint positions, their velocities and their
  rotations alone, which tells what leaves the data first;
* **APD** of the futures over their first 5 s (the paper's diversity; a model that halts or
  repeats one future scores low);
* **at the box** after 60 s, for a denoiser that clamps its frames (``clip_x0``): the share of
  the root's d_x, d_y, d_r over the last tail that sit on the clamp's edge, where a future
  that runs away can end up pressed against the training frames' range.

:func:`locomotion_report` returns one record per take, per content and for all takes;
``benchmarks/locomotion.py`` prints them as JSON lines. Any motion checkpoint runs: A-MDM, the
MVAE-style and MSE baselines (:func:`~minimdm.amdm.sampling.rollout`) and AAMDM
(:func:`~minimdm.aamdm.eval.rollout_aamdm`).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from minimdm.checkpoint import Checkpoint
from minimdm.diffusion import clip_bounds
from minimdm.motion import metrics
from minimdm.motion.corpora import LOCOMOTION, load_motion
from minimdm.motion.data import Clip, MotionDataset
from minimdm.motion.features import FeatureLayout, Normalizer, StartPose, encode, start_pose_of
from minimdm.validate import InputError, MismatchError

__all__ = [
    "LOCOMOTION",
    "LocomotionProtocol",
    "locomotion_takes",
    "check_corpus_match",
    "take_reference",
    "speed_curve",
    "locomotion_report",
    "pace_slope",
    "one_step_pace",
    "ContentIndex",
    "STUDY_COLUMNS",
    "study_grid",
    "YARDSTICK_COLUMNS",
    "yardstick_table",
]


@dataclass
class LocomotionProtocol:
    """What :func:`locomotion_report` runs (defaults: the issue's yardstick, about a minute)."""

    start_frame: int = 45
    """Clip frame of each take that the rollouts start from (1.5 s in at 30 fps)."""
    n_samples: int = 4
    """Futures per take."""
    seconds: float = 10.0
    """The scored rollout: speed over its tail, foot sliding, acceleration and bone error."""
    long_seconds: float = 60.0
    """The whole rollout, for staying power (<= ``seconds``: no long rollout)."""
    tail_seconds: float = 3.0
    """The window at the end of each rollout over which speed is measured."""
    moving_ratio: float = 0.5
    """A future still moves when its tail speed is at least this share of the take's."""
    seed: int = 0
    """Seeds the sampler."""
    steps: int | None = None
    """Denoising steps per frame (None: the model's own)."""
    eta: float = 1.0
    """DDIM stochasticity when ``steps`` is below T (1: as DDPM; 0: deterministic steps)."""
    corpus: str | None = None
    """The labelled corpus whose takes start the rollouts (None: the checkpoint's)."""
    split: str = "test"
    """Which of its takes: 'test' (held out: the yardstick), or 'train' (held in: a diagnostic
    that tells a model which cannot hold a recording's pace from one that cannot generalise to
    an unseen actor and content). Takes too short to start at ``start_frame`` are left out and
    named in the report's ``skipped``."""

    def __post_init__(self) -> None:
        if self.start_frame < 1 or self.n_samples < 1:
            raise InputError(
                f"start_frame and n_samples must be >= 1, got {self.start_frame}, {self.n_samples}"
            )
        if not 0 < self.tail_seconds <= self.seconds:
            raise InputError(
                f"tail_seconds must lie in (0, seconds={self.seconds}], got {self.tail_seconds}"
            )
        if self.split not in ("test", "train"):
            raise InputError(f"split must be 'test' or 'train', got {self.split!r}")


def locomotion_takes(corpus: str, fps: float | None = None, split: str = "test") -> MotionDataset:
    """The ``split`` takes of a labelled corpus whose content is locomotion (:data:`LOCOMOTION`),
    in table order, at ``fps`` (None: as recorded)."""
    takes = load_motion(corpus, split=split, fps=fps)
    keep = [c for c in takes if c.labels.get("content") in LOCOMOTION]
    if not keep:
        raise InputError(
            f"corpus {corpus!r} ({split} split) holds no take labelled with a locomotion "
            f"content {LOCOMOTION}"
        )
    keep.sort(key=lambda c: (LOCOMOTION.index(c.labels["content"]), c.name))
    return MotionDataset(keep)


def check_corpus_match(ckpt: Checkpoint, clip: Clip, corpus: str) -> FeatureLayout:
    """The checkpoint's feature layout, after checking that it fits the corpus's takes: the same
    joints in the same order and the same frame rate; a mismatch names both."""
    where = f"checkpoint {ckpt.paths.weights}"
    if ckpt.feature_layout is None:
        raise InputError(f"{where} records no feature layout: it is not a motion model")
    layout = FeatureLayout.from_dict(ckpt.feature_layout)
    joints = tuple(clip.skeleton.names)
    if layout.joint_names != joints:
        raise MismatchError(
            f"{where} was trained on a skeleton of {layout.n_joints} joints "
            f"({', '.join(layout.joint_names[:4])}, ...), but corpus {corpus!r} has "
            f"{len(joints)} ({', '.join(joints[:4])}, ...)"
        )
    if abs(layout.fps - clip.fps) > 1e-3 * layout.fps:  # a BVH frame time of 0.0333333 s
        raise MismatchError(
            f"{where} runs at {layout.fps:g} frames/s, but corpus {corpus!r} was recorded at "
            f"{clip.fps:g}"
        )
    return layout


def speed_curve(features: Tensor, fps: float, window: int) -> Tensor:
    """Root ground speed in m/s, averaged over consecutive windows of ``window`` frames.

    ``features`` (..., F, D) in feature units; returns (..., F // window).
    """
    speed = features[..., 0:2].norm(dim=-1) * fps  # (..., F)
    n = speed.shape[-1] // window
    return speed[..., : n * window].unflatten(-1, (n, window)).mean(-1)


def take_reference(clip: Clip, foot_offset: list[float]) -> dict[str, Any]:
    """A take's own measures: mean speed (m/s), mean heading-frame velocity (m/s), foot
    sliding, joint acceleration and its actor's bone lengths."""
    feats = encode(clip).double()  # (F - 1, D)
    vel = feats[:, 0:2] * clip.fps  # (F - 1, 2) m/s in the heading frame
    sk = clip.skeleton
    return {
        "speed": float(vel.norm(dim=-1).mean()),
        "velocity": vel.mean(0),
        "FS": metrics.foot_sliding(clip.positions, sk.foot_indices, foot_offset=foot_offset),
        "Jnt.Accel": metrics.joint_acceleration(clip.positions),
        "bones": metrics.skeleton_bone_lengths(sk.offsets, sk.parents),
    }


class ContentIndex:
    """Which content a frame looks like: the content of its nearest frame among a labelled
    corpus's training takes (Euclidean, over every feature scaled by its spread in those takes).

    :meth:`classify` gives the index in :data:`LOCOMOTION` of that frame's take, or -1 where
    the take is not locomotion (a gesture, a dance, a fall). On the held-out locomotion takes
    of bandai-namco-1 about 98% of the frames find a locomotion take, and two in three their
    own content: a run is often nearest a dash, a sidestep nearest a walk.

    Every frame also knows its take (:meth:`takes`): ``take_pace`` (T,) is each training take's
    mean ground speed in m/s and ``take_style`` (T,) its ``style`` label, so that a future's
    frames can be read as "it looks like take t", and its speed compared with that take's.
    """

    def __init__(self, corpus: str, split: str = "train") -> None:
        frames, labels, takes, pace, styles = [], [], [], [], []
        for t, clip in enumerate(load_motion(corpus, split=split)):
            feats = encode(clip).float()  # (F - 1, D)
            content = clip.labels.get("content")
            frames.append(feats)
            labels.append(
                torch.full(
                    (len(feats),), LOCOMOTION.index(content) if content in LOCOMOTION else -1
                )
            )
            takes.append(torch.full((len(feats),), t))
            pace.append(float((feats[:, 0:2].double().norm(dim=-1) * clip.fps).mean()))
            styles.append(clip.labels.get("style"))
        if not frames:
            raise InputError(f"corpus {corpus!r} ({split} split) holds no takes")
        x = torch.cat(frames)
        self.mean, self.std = x.mean(0), x.std(0).clamp_min(1e-6)
        self.frames = (x - self.mean) / self.std  # (N, D)
        self.labels = torch.cat(labels)  # (N,)
        self.take = torch.cat(takes)  # (N,) the take of each frame
        self.take_pace = torch.tensor(pace, dtype=torch.float64)  # (T,) m/s
        self.take_style = styles  # (T,)

    def gaps(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """The content index (...,) of frames ``features`` (..., D) in feature units, and
        their difference (..., D) from that nearest training frame, each feature in its spread:
        0 for a training frame itself."""
        labels, _, gap = self.read(features)
        return labels, gap

    def read(self, features: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """What :meth:`gaps` gives, with the take (...,) of each nearest training frame in
        between: its index into ``take_pace`` and ``take_style``."""
        flat = ((features.float() - self.mean) / self.std).reshape(-1, self.frames.shape[1])
        where = torch.cat([torch.cdist(c, self.frames).argmin(1) for c in flat.split(1024)])
        gap = flat - self.frames[where]
        shape = features.shape[:-1]
        return (
            self.labels[where].reshape(shape),
            self.take[where].reshape(shape),
            gap.reshape(features.shape),
        )

    def takes(self, features: Tensor) -> Tensor:
        """The take (...,) whose frame is nearest each of ``features`` (..., D)."""
        return self.read(features)[1]

    def nearest(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """The content index (...,) of frames ``features`` (..., D) and their distance (...,)
        to that nearest training frame: the root mean square of :meth:`gaps` over the
        features."""
        labels, gap = self.gaps(features)
        return labels, _rms(gap)

    def classify(self, features: Tensor) -> Tensor:
        """The content index (..., ) of frames ``features`` (..., D) in feature units."""
        return self.nearest(features)[0]


def _rms(gap: Tensor) -> Tensor:
    """The root mean square (...,) over the last dimension."""
    return gap.pow(2).mean(-1).sqrt()


def _feature_groups(layout: FeatureLayout) -> dict[str, slice]:
    """The feature groups whose distance off the data the yardstick reports one by one."""
    root = slice(layout.root_vel.start, layout.yaw_rate.stop)
    return {
        "root": root,
        "positions": layout.joint_pos,
        "velocities": layout.joint_vel,
        "rotations": layout.joint_rot,
    }


_INDEXES: dict[str, ContentIndex] = {}


def _content_index(corpus: str) -> ContentIndex:
    """The training takes' :class:`ContentIndex` of a corpus, built once per process."""
    if corpus not in _INDEXES:
        _INDEXES[corpus] = ContentIndex(corpus)
    return _INDEXES[corpus]


def _resembled(
    index: ContentIndex, near: Tensor, speed: Tensor, style: str | None, when: str
) -> dict[str, float]:
    """Whom the futures look like: the mean pace (m/s) of the training takes nearest the
    frames ``near`` (K, F) of K futures (or of the take itself, K = 1), the futures' speed
    ``speed`` (K,) over that pace (1: as fast as the takes its poses come from; far above 1:
    gliding in another take's poses), and the share of frames on a take of the start's
    ``style``."""
    pace = index.take_pace[near].mean(-1)  # (K,)
    same = torch.tensor([[index.take_style[t] == style for t in r] for r in near.tolist()])
    return {
        f"resembled_pace_{when}": float(pace.mean()),
        f"pace_vs_poses_{when}": float((speed.double() / pace.clamp_min(1e-6)).mean()),
        f"style_{when}": float(same.double().mean()) if style is not None else float("nan"),
    }


def _shares(labels: Tensor, own: int) -> tuple[float, float]:
    """The share of frames on any locomotion content, and on the content ``own``."""
    return float((labels >= 0).double().mean()), float((labels == own).double().mean())


def _generate(ckpt: Checkpoint, takes: MotionDataset, p: LocomotionProtocol, n_frames: int):
    """Rollouts (C, K, F, D) features and (C, K, F, J, 3) positions from every take."""
    gen = torch.Generator().manual_seed(p.seed)
    f0 = p.start_frame
    starts = [start_pose_of(c, f0) for c in takes]
    start = StartPose(
        torch.stack([torch.as_tensor(s.xy, dtype=torch.float64) for s in starts]),
        torch.stack([torch.as_tensor(s.heading, dtype=torch.float64) for s in starts]),
    )
    if ckpt.kind == "aamdm_motion":
        from minimdm.aamdm.eval import rollout_aamdm
        from minimdm.aamdm.motion import clip_trajectory_features

        model = ckpt.model.eval()
        y = torch.stack([encode(c)[f0 - 1] for c in takes]).float()  # (C, D)
        x = torch.stack([clip_trajectory_features(c)[f0 - 1] for c in takes]).float()
        r = rollout_aamdm(model, y, x, n_frames, p.n_samples, gen, start_pose=start)
    else:
        from minimdm.amdm.sampling import history_of, rollout

        H = history_of(ckpt.model)  # a model that conditions on H frames gets H of them
        rows = slice(f0 - 1, f0) if H == 1 else slice(f0 - H, f0)
        init = torch.stack([encode(c)[rows] for c in takes]).float()  # (C, [H,] D)
        init = init[:, 0] if H == 1 else init
        r = rollout(
            ckpt,
            init,
            n_frames,
            p.n_samples,
            steps=p.steps,
            eta=p.eta,
            generator=gen,
            start_pose=start,
        )
    return r.features.double(), r.positions.double()


def _ratio(a: float, b: float) -> float:
    return float(a / b) if b > 0 else float("nan")


@torch.no_grad()
def one_step_pace(
    ckpt: Checkpoint, corpus: str | None = None, n_samples: int = 4, seed: int = 0
) -> dict[str, dict[str, float]]:
    """The pace of one step from the recording: does the model speed up or slow down where its
    condition is recorded, or only where it is its own?

    For every frame of every held-out locomotion take that has ``history`` frames before it,
    ``n_samples`` next frames are drawn from the recorded frames before it (teacher forcing, no
    rollout), and the root's ground speed of the draws (``root_vel``, m/s) is compared with the
    recorded next frame's. Returns, per content and for ``"all"`` takes, ``take_speed`` (the
    recorded speed), ``one_step_speed`` (the draws') and ``one_step_ratio`` (their quotient).
    A ratio near 1 with a rollout that runs away (the yardstick's ``speed_ratio_10s``) says the
    drift comes from the model's own frames, not from a bias it learned on recorded ones.
    """
    from minimdm.amdm.sampling import Sampler

    n_samples = int(n_samples)
    if n_samples < 1:
        raise InputError(f"n_samples must be >= 1, got {n_samples}")
    corpus = corpus or ckpt.config.get("corpus")
    takes = locomotion_takes(corpus)
    check_corpus_match(ckpt, takes[0], corpus)
    sampler = Sampler.load(ckpt)
    H, fps = sampler.history, sampler.fps
    gen = torch.Generator(device=sampler.device).manual_seed(seed)
    sums: dict[str, list[float]] = {}
    for clip in takes:
        f = encode(clip).float()  # (F, D): row i is clip frame i + 1
        if len(f) <= H:
            continue
        n = sampler.normalize(f.to(sampler.device))
        cond = torch.stack([n[i - H : i].flatten() for i in range(H, len(f))])  # (N, H D)
        x = sampler.frame(cond.repeat_interleave(n_samples, 0), gen)  # (N K, D)
        drawn = sampler.denormalize(x).cpu()[:, :2].norm(dim=-1).sum() / n_samples
        recorded = f[H:, :2].norm(dim=-1).sum()
        for key in (clip.labels["content"], "all"):
            acc = sums.setdefault(key, [0.0, 0.0])
            acc[0], acc[1] = acc[0] + float(drawn), acc[1] + float(recorded)
    out = {}
    for key in [c for c in LOCOMOTION if c in sums] + ["all"]:
        drawn, recorded = sums[key]
        out[key] = {
            "take_speed": recorded * fps / _frames(takes, key, H),
            "one_step_speed": drawn * fps / _frames(takes, key, H),
            "one_step_ratio": _ratio(drawn, recorded),
        }
    return out


def _frames(takes: MotionDataset, content: str, history: int) -> int:
    """How many frames :func:`one_step_pace` draws for a content ("all": every take)."""
    return sum(
        max(0, c.n_frames - 1 - history)
        for c in takes
        if content == "all" or c.labels["content"] == content
    )


def locomotion_report(ckpt: Checkpoint, protocol: LocomotionProtocol | None = None) -> dict:
    """Run the locomotion yardstick on a motion checkpoint (see the module docstring).

    Returns ``{"takes": [...], "contents": {content: {...}}, "all": {...}, "protocol": {...},
    "seconds": wall time}``. Speeds are m/s; ``*_ratio`` divide by the take's own value; FS is
    cm/frame, Jnt.Accel cm/frame², Bone.Err cm.
    """
    p = protocol or LocomotionProtocol()
    corpus = p.corpus or ckpt.config.get("corpus")
    if not corpus or corpus == "deepmimic":
        raise InputError(
            f"checkpoint {ckpt.paths.weights} was trained on {corpus!r}, which has no labelled "
            "locomotion takes: pass a corpus (e.g. corpus='bandai-namco-1')"
        )
    takes = locomotion_takes(corpus, split=p.split)  # at the recorded rate: the model's
    layout = check_corpus_match(ckpt, takes[0], corpus)
    skipped = [c.name for c in takes if c.n_frames <= p.start_frame + 1]
    if len(skipped) == len(takes):
        raise InputError(f"start_frame {p.start_frame} is past the end of every take {skipped}")
    if skipped:
        takes = MotionDataset([c for c in takes if c.n_frames > p.start_frame + 1])
    fps = layout.fps
    n_short = round(p.seconds * fps)
    n_frames = max(n_short, round(p.long_seconds * fps))
    tail = round(p.tail_seconds * fps)
    sk = takes[0].skeleton
    offset = metrics.foot_contact_offsets(
        np.concatenate([c.positions for c in takes]), sk.foot_indices
    )
    t0 = time.perf_counter()
    feats, pos = _generate(ckpt, takes, p, n_frames)  # (C, K, F, D), (C, K, F, J, 3)
    on_box = _on_box(ckpt, feats[..., n_frames - tail : n_frames, :])  # (C,) or None
    gen_seconds = time.perf_counter() - t0
    second = round(fps)
    index = _content_index(corpus)
    groups = _feature_groups(layout)
    rows = []
    for i, clip in enumerate(takes):
        ref = take_reference(clip, offset)
        own = LOCOMOTION.index(clip.labels["content"])
        f_i, x_i = feats[i], pos[i]  # (K, F, D), (K, F, J, 3)
        v = f_i[..., 0:2] * fps  # (K, F, 2) heading-frame velocity, m/s
        speed = v.norm(dim=-1)  # (K, F)
        dir_ = ref["velocity"] / ref["velocity"].norm().clamp_min(1e-9)  # (2,)
        along = (v * dir_).sum(-1)  # (K, F) velocity along the take's own direction

        def tail_mean(x: Tensor, end: int) -> Tensor:  # (K,) mean over the tail ending at end
            return x[:, end - tail : end].mean(1)

        s10 = tail_mean(speed, n_short)
        short_pos = x_i[:, :n_short]
        row = {
            "take": clip.name,
            "content": clip.labels["content"],
            "style": clip.labels.get("style"),
            "take_speed": ref["speed"],
            "speed_10s": float(s10.mean()),
            "speed_ratio_10s": _ratio(float(s10.mean()), ref["speed"]),
            "along_ratio_10s": _ratio(float(tail_mean(along, n_short).mean()), ref["speed"]),
            "speed_by_second": speed_curve(f_i, fps, second).mean(0).tolist(),
            "FS": metrics.foot_sliding(short_pos, sk.foot_indices, foot_offset=offset),
            "FS_data": ref["FS"],
            "Jnt.Accel": metrics.joint_acceleration(short_pos),
            "Jnt.Accel_data": ref["Jnt.Accel"],
            "Bone.Err": metrics.bone_length_error(short_pos, sk.parents, ref["bones"]),
        }
        labels, near, gap = index.read(f_i[:, n_short - tail : n_short])
        data_labels, data_near, data_gap = index.read(encode(clip))
        on_loco, kept = _shares(labels, own)
        data_loco, data_kept = _shares(data_labels, own)
        row |= {"locomotion_10s": on_loco, "locomotion_data": data_loco}
        row |= {"content_10s": kept, "content_data": data_kept}
        style = clip.labels.get("style")
        row |= _resembled(index, near, s10, style, "10s")
        row |= _resembled(index, data_near[None], torch.tensor([ref["speed"]]), style, "data")
        row |= {
            "pose_dist_10s": float(_rms(gap).mean()),
            "pose_dist_data": float(_rms(data_gap).mean()),
        }
        for name, cols in groups.items():  # which features leave the data
            row[f"pose_dist_10s_{name}"] = float(_rms(gap[..., cols]).mean())
            row[f"pose_dist_data_{name}"] = float(_rms(data_gap[..., cols]).mean())
        if p.n_samples > 1:  # how far the futures spread over the paper's 150 frames (5 s)
            row["APD"] = metrics.apd(x_i[:, : min(150, n_short)])
        if n_frames > n_short:
            s60 = tail_mean(speed, n_frames)
            row["speed_60s"] = float(s60.mean())
            row["speed_ratio_60s"] = _ratio(row["speed_60s"], ref["speed"])
            row["along_ratio_60s"] = _ratio(float(tail_mean(along, n_frames).mean()), ref["speed"])
            row["moving_60s"] = float((s60 >= p.moving_ratio * ref["speed"]).double().mean())
            row["Bone.Err_60s"] = metrics.bone_length_error(x_i, sk.parents, ref["bones"])
            labels, near, gap = index.read(f_i[:, n_frames - tail :])
            row["locomotion_60s"] = _shares(labels, own)[0]
            row["pose_dist_60s"] = float(_rms(gap).mean())
            row |= _resembled(index, near, s60, style, "60s")
            if on_box is not None:
                row["at_box_60s"] = float(on_box[i])
        rows.append(row)
    contents = {c: _pool([r for r in rows if r["content"] == c]) for c in LOCOMOTION}
    return {
        "checkpoint": str(ckpt.paths.weights.parent),
        "kind": ckpt.kind,
        "protocol": asdict(p) | {"corpus": corpus},
        "takes": rows,
        "contents": contents,
        "all": _pool(rows) | {"pace_slope_10s": pace_slope(contents)},
        "skipped": skipped,
        "seconds": round(gen_seconds, 1),
    }


def _on_box(ckpt: Checkpoint, tail: Tensor) -> Tensor | None:
    """Per take (C,), the share of the root's d_x, d_y, d_r in the rollout ``tail`` (C, K, F,
    D), feature units, on the edge of the box the denoiser clamps its frames to (within a
    thousandth of a feature's spread); None for a model without one."""
    box = ckpt.diffusion.get("clip_x0")
    if box is None or ckpt.normalizer is None:
        return None
    bounds = clip_bounds(box, tail.shape[-1], dtype=torch.float64)
    if isinstance(bounds, float):  # the box [-c, c]
        bounds = (torch.full((3,), -bounds), torch.full((3,), bounds))
    lo, hi = bounds
    x = Normalizer.from_dict(ckpt.normalizer).normalize(tail.float()).double()[..., :3]
    edge = (x <= lo[:3] + 1e-3) | (x >= hi[:3] - 1e-3)
    return edge.double().mean((1, 2, 3))


def _pool(rows: list[dict]) -> dict[str, float]:
    """Mean over takes of every number, plus the worst take's speed ratio and the generated
    FS and acceleration divided by the data's (ratios of means)."""
    if not rows:
        return {}
    keys = [k for k, v in rows[0].items() if isinstance(v, (int, float))]
    out = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    out["n_takes"] = len(rows)
    out["worst_speed_ratio_10s"] = float(min(r["speed_ratio_10s"] for r in rows))
    out["FS_ratio"] = _ratio(out["FS"], out["FS_data"])
    out["Jnt.Accel_ratio"] = _ratio(out["Jnt.Accel"], out["Jnt.Accel_data"])
    out["off_data_10s"] = _ratio(out["pose_dist_10s"], out["pose_dist_data"])
    for key in [k for k in out if k.startswith("pose_dist_10s_")]:
        name = key.removeprefix("pose_dist_10s_")
        out[f"off_data_10s_{name}"] = _ratio(out[key], out[f"pose_dist_data_{name}"])
    if "speed_ratio_60s" in rows[0]:
        out["worst_speed_ratio_60s"] = float(min(r["speed_ratio_60s"] for r in rows))
        out["off_data_60s"] = _ratio(out["pose_dist_60s"], out["pose_dist_data"])
    return out


def pace_slope(contents: dict[str, dict[str, Any]]) -> float | None:
    """How much of each content's own pace the futures keep after 10 s.

    ``contents`` maps a content to its pool (``take_speed`` and ``speed_10s``, m/s, as in
    :func:`locomotion_report`). Returns the least-squares slope of ``log speed_10s`` against
    ``log take_speed`` over the contents that have both: 1 where every content keeps its own
    pace (or all are off by one factor), 0 where every start ends at one pace, negative where
    the slow contents end faster than the fast ones. None with fewer than two such contents
    of different speeds.
    """
    pairs = [(c["take_speed"], c["speed_10s"]) for c in contents.values() if "speed_10s" in c]
    if len(pairs) < 2:
        return None
    x, y = np.log(np.array(pairs, dtype=float).clip(min=1e-6)).T
    if np.ptp(x) == 0:
        return None
    return float(np.polyfit(x, y, 1)[0])


STUDY_COLUMNS = {
    "speed 10 s": "speed_ratio_10s",
    "worst take": "worst_speed_ratio_10s",
    "pace kept": "pace_slope_10s",
    "speed 60 s": "speed_ratio_60s",
    "moving 60 s": "moving_60s",
    "FS ×data": "FS_ratio",
    "accel ×data": "Jnt.Accel_ratio",
    "bone cm": "Bone.Err",
    "APD 5 s": "APD",
    "at box 60 s": "at_box_60s",
    "on loco 10 s": "locomotion_10s",
    "on loco 60 s": "locomotion_60s",
    "content kept": "content_10s",
    "style kept": "style_10s",
    "pace ÷ poses'": "pace_vs_poses_10s",
    "off data 10 s": "off_data_10s",
    "off data 60 s": "off_data_60s",
    "off root 10 s": "off_data_10s_root",
    "off pos 10 s": "off_data_10s_positions",
    "off vel 10 s": "off_data_10s_velocities",
    "off rot 10 s": "off_data_10s_rotations",
}
"""The study grid's columns (header: key of a yardstick record's ``all`` pool)."""


def study_grid(path: str | Path, names: list[str] | None = None) -> dict[str, dict[str, Any]]:
    """The base-model study's grid from ``benchmarks/results/amdm_study.jsonl``.

    One row per run (``names`` in that order, default: every run in file order): the yardstick
    columns of :data:`STUDY_COLUMNS` as ``(mean, std)`` over the sampling seeds scored (a plain
    number where one seed has the column), the number of seeds, and Table 1's APD, ADE and
    FDE in cm where the run was also scored with ``--table1`` (their std is over Table 1's own
    3 seeds). A run scored twice with one seed keeps the later row. Ready for
    :func:`minimdm.utils.format_table`.
    """
    loco, table1 = _study_records(path)
    order = list(names) if names is not None else list(dict.fromkeys([*loco, *table1]))
    out: dict[str, dict[str, Any]] = {}
    for name in order:
        if name not in loco and name not in table1:
            raise ValueError(f"{path} holds no row of the run {name!r}")
        row: dict[str, Any] = {}
        seeds = [_with_pace(rec) for rec in loco.get(name, {}).values()]
        for header, key in STUDY_COLUMNS.items():
            row[header] = _over_seeds([s[key] for s in seeds if s.get(key) is not None])
        row["seeds"] = len(seeds)
        for k in ("APD", "ADE", "FDE"):
            cell = table1.get(name, {}).get(k)
            row[f"T1 {k}"] = (cell["mean"], cell["std"]) if cell else None
        out[name] = row
    return out


def study_table1(path: str | Path, names: list[str]) -> dict[str, dict[str, tuple[float, float]]]:
    """Table 1 of the study runs ``names`` scored with ``--table1``: every metric as ``(mean,
    std)`` over Table 1's 3 seeds, in Table 1's column order, the shape of
    :func:`minimdm.studies.amdm_tables.read_results`, so that a study run and the shipped
    models' rows can share one table."""
    from minimdm.amdm.evaluation import TABLE1_COLUMNS

    _, table1 = _study_records(path)
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for name in names:
        if name not in table1:
            raise ValueError(f"{path} holds no Table 1 row of the run {name!r}")
        cells = {k: (v["mean"], v["std"]) for k, v in table1[name].items()}
        out[name] = {c: cells[c] for c in TABLE1_COLUMNS if c in cells}
    return out


def study_contents(
    path: str | Path,
    names: list[str],
    key: str = "speed_ratio_10s",
    contents: tuple[str, ...] = LOCOMOTION,
) -> dict[str, dict[str, Any]]:
    """One number of the yardstick per content for each study run of ``names``: ``key`` of its
    content pools (default: the speed held at 10 s, as a share of the takes' own) as
    ``(mean, std)`` over the sampling seeds scored, or a plain number for one seed. Ready for
    :func:`minimdm.utils.format_table`."""
    loco, _ = _study_records(path)
    out: dict[str, dict[str, Any]] = {}
    for name in names:
        if name not in loco:
            raise ValueError(f"{path} holds no yardstick row of the run {name!r}")
        seeds = list(loco[name].values())
        out[name] = {c: _over_seeds([s["contents"][c][key] for s in seeds]) for c in contents}
    return out


def _with_pace(rec: dict) -> dict:
    """A study record's ``all`` pool with the pace kept, from its content pools where the row
    was written before the yardstick measured it."""
    pool = rec["all"]
    if "pace_slope_10s" not in pool and rec.get("contents"):
        pool = pool | {"pace_slope_10s": pace_slope(rec["contents"])}
    return pool


def _study_records(path: str | Path) -> tuple[dict[str, dict[int, dict]], dict[str, dict]]:
    """The study file's yardstick records by run and sampling seed (a later row of the same
    seed wins), and its Table 1 records by run."""
    loco: dict[str, dict[int, dict]] = {}
    table1: dict[str, dict] = {}
    for line in Path(path).read_text().splitlines():
        rec = json.loads(line)
        if "table1" in rec:
            table1[rec["name"]] = rec["table1"]
        elif "all" in rec:
            loco.setdefault(rec["name"], {})[rec["protocol"]["seed"]] = rec
    return loco, table1


def _over_seeds(vals: list[float]) -> tuple[float, float] | float | None:
    """``(mean, std)`` of several seeds' values, the value of one, None of none."""
    if len(vals) > 1:
        return float(np.mean(vals)), float(np.std(vals))
    return float(vals[0]) if vals else None


YARDSTICK_COLUMNS = {
    "speed 10 s": "speed_ratio_10s",
    "worst take": "worst_speed_ratio_10s",
    "moving 60 s": "moving_60s",
    "speed 60 s": "speed_ratio_60s",
    "FS cm": "FS",
    "FS data": "FS_data",
    "accel": "Jnt.Accel",
    "accel data": "Jnt.Accel_data",
    "bone cm": "Bone.Err",
}
"""The yardstick table's columns (header: key of a content or ``all`` record)."""


def yardstick_table(
    path: str | Path,
    tag: str,
    checkpoints: dict[str, str],
    contents: tuple[str, ...] = LOCOMOTION,
    columns: dict[str, str] | None = None,
) -> dict[str, dict[str, Any]]:
    """Per content and model, the yardstick rows of ``benchmarks/locomotion.py`` with one tag.

    Args:
        path: the JSON-lines file (``benchmarks/results/locomotion.jsonl``).
        tag: the rows' ``tag`` (a file holds several rounds).
        checkpoints: ``{row label: checkpoint path as recorded}``, in table order.
        contents: the contents, in table order, then ``"all"`` (every take pooled).
        columns: ``{header: record key}`` (default :data:`YARDSTICK_COLUMNS`).

    Returns ``{"content, label": {column: (mean, std) over the sampling seeds, "seeds": n}}``
    with the columns of :data:`YARDSTICK_COLUMNS`: speeds as ratios of the take's own, foot
    sliding and joint acceleration of the model beside the same takes' own (cm, cm/frame²).
    """
    columns = YARDSTICK_COLUMNS if columns is None else columns
    found: dict[tuple[str, str], list[dict]] = {}
    for line in Path(path).read_text().splitlines():
        rec = json.loads(line)
        if rec.get("tag") != tag or rec.get("scope") not in ("content", "all"):
            continue
        content = rec.get("content", "all") if rec["scope"] == "content" else "all"
        found.setdefault((rec["checkpoint"], content), []).append(rec)
    out: dict[str, dict[str, Any]] = {}
    for content in (*contents, "all"):
        for label, ck in checkpoints.items():
            recs = found.get((ck, content))
            if not recs:
                raise ValueError(f"{path} holds no {tag!r} row of {ck} for {content!r}")
            row: dict[str, Any] = {}
            for header, key in columns.items():
                vals = [r[key] for r in recs]
                row[header] = (float(np.mean(vals)), float(np.std(vals)))
            row["seeds"] = len(recs)
            out[f"{content}, {label}"] = row
    return out
