"""Task-oriented sampling (A-MDM §4.2, §7.3.3; Ling et al. 2020): a pool of futures, scored.

At every frame the model proposes ``pool`` candidate futures of ``horizon`` frames from the
current state, all sampled in one batch; a user score function ranks them; the first frame of
the best one becomes the next state, and the search repeats. With ``horizon = 1`` this is the
paper's experiment (100 candidate successor states, the one closest to the target kept).

A score function is any callable ``score_fn(future) -> (b, P)`` tensor, **higher is better**,
where ``future`` is a :class:`Future`: the candidates' features and, decoded from the current
root pose, their root path, headings and joint positions. :mod:`minimdm.control.scores` has
target reaching, heading and speed.

The search is two plain loops, the notebook's ``my_search`` with its bookkeeping: the outer
one searches, then commits the first ``commit`` frames of each character's best plan; the inner
one (:func:`_propose`) samples the candidates' H frames, the whole (b P) batch at once, with
:meth:`~minimdm.amdm.sampling.Sampler.frame`. Every sampled frame goes through the library's
one non-finite check, :func:`~minimdm.amdm.sampling.check_finite`, which names the frame, the
character and the candidate.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from minimdm.amdm.sampling import Sampler, check_finite
from minimdm.checkpoint import Checkpoint
from minimdm.motion.features import StartPose, decode, decode_root
from minimdm.validate import InputTypeError, describe

from .core import Motion, as_start, check_count

__all__ = ["Future", "beam_search"]


@dataclass
class Future:
    """Candidate futures of the b characters still searching: P candidates of H frames each."""

    features: Tensor
    """(b, P, H, D) candidate frames x_{f+1}..x_{f+H}, feature units."""
    start_xy: Tensor
    """(b, 2) the current root ground position (of x_f)."""
    start_heading: Tensor
    """(b,) the current heading."""
    index: Tensor
    """(b,) which characters of the batch these are (per-character goals use goal[index])."""
    frame: int
    """f: frames committed so far; the candidates' first frame becomes frame f + 1."""
    fps: float = 30.0
    """Frame rate of the features."""

    @property
    def pool(self) -> int:
        return self.features.shape[1]

    @property
    def horizon(self) -> int:
        return self.features.shape[2]

    def _start(self) -> StartPose:
        return StartPose(self.start_xy[:, None], self.start_heading[:, None])  # (b, 1, ...)

    @cached_property
    def _root(self) -> tuple[Tensor, Tensor]:
        return decode_root(self.features.double(), self._start())

    @property
    def root_xy(self) -> Tensor:
        """(b, P, H, 2) root ground positions along each candidate, metres."""
        return self._root[0]

    @property
    def heading(self) -> Tensor:
        """(b, P, H) headings along each candidate, radians."""
        return self._root[1]

    @property
    def velocity(self) -> Tensor:
        """(b, P, H, 2) root planar velocity in m/s (world frame), from the current position."""
        prev = torch.cat(
            [
                self.start_xy[:, None, None].expand_as(self.root_xy[:, :, :1]),
                self.root_xy[:, :, :-1],
            ],
            dim=2,
        )
        return (self.root_xy - prev) * self.fps

    @cached_property
    def positions(self) -> Tensor:
        """(b, P, H, J, 3) global joint positions, metres."""
        return decode(self.features.double(), self._start())


ScoreFn = Callable[[Future], Tensor]
StopFn = Callable[[Future], Tensor]


@torch.no_grad()
def beam_search(
    model: Checkpoint | Sampler | nn.Module | str | os.PathLike,
    start: Tensor,
    score_fn: ScoreFn,
    n_frames: int,
    pool: int = 32,
    horizon: int = 1,
    generator: torch.Generator | None = None,
    *,
    commit: int = 1,
    start_pose: StartPose | dict | None = None,
    stop_fn: StopFn | None = None,
    progress: bool = False,
) -> Motion:
    """Task-oriented sampling: keep the first frame of the best of ``pool`` futures, repeat.

    Args:
        model: a loaded Checkpoint (normalizer, schedule, predicts, clip_x0 come from it), a
            path, a :class:`Sampler` (e.g. with fewer ``steps`` or a regressor ``noise``),
            or a bare network.
        start: (D,) or (B, D) start state x_0 in feature units; B characters search at once.
        score_fn: ``score_fn(future) -> (b, P)``, higher is better (module docstring).
        n_frames: frames to generate, >= 1.
        pool: P, candidates per search, >= 1 (A-MDM §7.3.3: 100).
        horizon: H, frames per candidate, >= 1 (the paper: 1).
        generator: randomness of the candidates.
        commit: frames of the best candidate kept before searching again, 1..H (the paper:
            1). A long horizon sees further; committing several of its frames makes it cheaper
            (receding-horizon control: P H / commit sampled frames per kept frame).
        start_pose: root ground position (B, 2) and heading (B,) of the start state.
        stop_fn: ``stop_fn(future) -> (b,)`` bool on each committed frame (P = H = 1): a
            character for which it is True has completed its task and stops searching, e.g.
            :func:`~minimdm.control.scores.reached`. Its remaining frames hold its last pose
            (root and joint velocities zeroed); ``info["done_at"]`` is the frame count at
            completion (-1: never). With one start state the motion ends at completion.
        progress: a tqdm bar over frames.

    Returns:
        A :class:`Motion`; ``info["score"]`` is the best score of the search that chose each
        frame (B, F), NaN after completion.
    """
    cm = Sampler.load(model)
    n_frames, P, H, commit = _check_counts(n_frames, pool, horizon, commit)
    _check_callables(score_fn, stop_fn)
    x0, batched, sp = as_start(cm, start, start_pose, generator)
    B, D = x0.shape
    x = cm.normalize(x0).clone()  # (B, D) the current states, normalized
    xy, heading = sp.xy.clone(), sp.heading.clone()  # (B, 2), (B,) their root pose
    out = torch.empty(B, n_frames, D, dtype=torch.float32)  # committed frames, normalized, CPU
    best_scores = torch.full((B, n_frames), float("nan"))  # the score that chose each frame
    done_at = torch.full((B,), -1, dtype=torch.long)
    f = 0  # frames committed
    with tqdm(total=n_frames, disable=not progress, desc="beam search", unit="frame") as bar:
        while f < n_frames and (done_at < 0).any():
            active = (done_at < 0).nonzero()[:, 0]  # (b,) the characters still searching
            cand = _propose(cm, x[active], P, H, f, generator, active)  # (b, P, H, D)
            future = Future(
                cm.denormalize(cand).float().cpu(), xy[active], heading[active], active, f, cm.fps
            )
            plan, plan_feats, score = _best(cand, future, score_fn(future))
            going = torch.arange(len(active))  # rows of the plan still committing frames
            for j in range(min(commit, n_frames - f)):  # receding horizon: its first frames
                rows = active[going]
                x[rows] = plan[going, j]  # characters that have stopped keep their state
                out[:, f] = x.float().cpu()
                best_scores[rows, f] = score[going]
                now = Future(
                    plan_feats[going, j][:, None, None], xy[rows], heading[rows], rows, f, cm.fps
                )
                xy[rows], heading[rows] = now.root_xy[:, 0, 0], now.heading[:, 0, 0]
                f += 1
                bar.update()
                if stop_fn is not None:
                    stop = _stopped(stop_fn(now), len(rows))
                    done_at[rows[stop]] = f
                    going = going[~stop]
    info = {"pool": P, "horizon": H, "commit": commit}
    return _motion(cm, out, best_scores, done_at, sp, batched, info)


def _check_counts(n_frames: int, pool: int, horizon: int, commit: int) -> tuple[int, ...]:
    """``n_frames``, ``pool``, ``horizon`` and ``commit`` checked: counts, commit <= horizon."""
    n_frames = check_count("n_frames", n_frames)
    P = check_count("pool", pool)
    H = check_count("horizon", horizon)
    commit = check_count("commit", commit)
    if commit > H:
        raise ValueError(f"commit must lie in [1, horizon={H}], got {commit}")
    return n_frames, P, H, commit


def _check_callables(score_fn: ScoreFn, stop_fn: StopFn | None) -> None:
    """``score_fn`` must be callable, ``stop_fn`` callable or None."""
    if not callable(score_fn):
        raise InputTypeError(f"score_fn must be callable, got {describe(score_fn)}")
    if stop_fn is not None and not callable(stop_fn):
        raise InputTypeError(f"stop_fn must be callable or None, got {describe(stop_fn)}")


def _propose(
    cm: Sampler,
    x: Tensor,
    P: int,
    H: int,
    f: int,
    generator: torch.Generator | None,
    active: Tensor,
) -> Tensor:
    """P candidate futures of H frames from each state ``x`` (b, D) after ``f`` committed
    frames: (b, P, H, D), normalized, each frame drawn by :meth:`Sampler.frame` from the last
    (A-MDM §3.1) for all b P candidates at once. ``active`` (b,) names the characters."""
    b, D = x.shape

    def who(r: int) -> str:
        return f"character {int(active[r // P])}, candidate {r % P}"

    frames = [x.repeat_interleave(P, dim=0)]  # (b P, D), character-major
    for h in range(1, H + 1):
        frames.append(check_finite(cm.frame(frames[-1], generator), f + h, who, "beam search"))
    return torch.stack(frames[1:], dim=1).reshape(b, P, H, D)


def _best(cand: Tensor, future: Future, scores: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Each character's best candidate by the score function's ``scores`` (b, P) of
    ``future`` (checked): its frames (b, H, D) normalized (from ``cand``, (b, P, H, D)) and
    in feature units, and its score (b,)."""
    b, P = future.features.shape[:2]
    scores = torch.as_tensor(scores).to("cpu", torch.float64)
    if scores.shape != (b, P):
        raise ValueError(f"score_fn must return shape (b={b}, P={P}), got {tuple(scores.shape)}")
    if torch.isnan(scores).any():
        raise ValueError(f"score_fn returned NaN at frame {future.frame + 1}")
    best = scores.argmax(dim=1)  # (b,)
    rows = torch.arange(b)
    return cand[rows, best.to(cand.device)], future.features[rows, best], scores[rows, best].float()


def _stopped(stop: Tensor, b: int) -> Tensor:
    """The stop function's answer as a (b,) bool tensor on the CPU (checked)."""
    stop = torch.as_tensor(stop, dtype=torch.bool).cpu().reshape(-1)
    if stop.shape != (b,):
        raise ValueError(f"stop_fn must return shape (b={b},), got {tuple(stop.shape)}")
    return stop


def _motion(
    cm: Sampler,
    out: Tensor,
    best_scores: Tensor,
    done_at: Tensor,
    sp: StartPose,
    batched: bool,
    info: dict,
) -> Motion:
    """The search's Motion from its committed frames ``out`` (B, F, D): a character that
    completed its task holds its last pose from then on (:func:`_hold`); with one start state
    the motion ends at completion."""
    feats = cm.denormalize(out)
    for i in torch.nonzero(done_at >= 0)[:, 0].tolist():
        k = int(done_at[i])
        feats[i, k:] = _hold(feats[i, k - 1])
        out[i, k:] = cm.normalize(feats[i, k:])
    n = out.shape[1] if batched or done_at[0] < 0 else int(done_at[0])
    info = {"score": best_scores[:, :n], "done_at": done_at, **info}
    if not batched:
        info = {**info, "score": info["score"][0], "done_at": int(done_at[0])}
    return Motion.from_normalized(cm, out[:, :n], sp, batched, info, features=feats[:, :n])


def _hold(frame: Tensor) -> Tensor:
    """``frame`` (D,) standing still: root velocity, yaw rate and joint velocities zeroed."""
    x = frame.clone()
    D = x.shape[-1]
    J = (D - 3) // 12
    x[:3] = 0
    x[3 + 3 * J : 3 + 6 * J] = 0
    return x
