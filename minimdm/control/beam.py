"""Task-oriented sampling (A-MDM §4.2, §7.3.3; Ling et al. 2020): a pool of futures, scored.

At every frame the model proposes ``pool`` candidate futures of ``horizon`` frames from the
current state, all sampled in one batch; a user score function ranks them; the first frame of
the best one becomes the next state, and the search repeats. With ``horizon = 1`` this is the
paper's experiment (100 candidate successor states, the one closest to the target kept).

A score function is any callable ``score_fn(future) -> (b, P)`` tensor, **higher is better**,
where ``future`` is a :class:`Future`: the candidates' features and, decoded from the current
root pose, their root path, headings and joint positions. :mod:`minimdm.control.scores` has
target reaching, heading and speed.

Both loops of the search run on the one rollout loop,
:func:`~minimdm.amdm.sampling.autoregress`: the candidates' horizon is a rollout of H frames of
the (b P) batch, and the search itself is the step of the outer rollout: at a frame where the
last plan has been committed, it searches and takes the best plan; at every frame it returns
that plan's next frame.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor, nn

from minimdm.amdm.sampling import Sampler, autoregress
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
    n_frames = check_count("n_frames", n_frames)
    P = check_count("pool", pool)
    H = check_count("horizon", horizon)
    commit = check_count("commit", commit)
    if commit > H:
        raise ValueError(f"commit must lie in [1, horizon={H}], got {commit}")
    if not callable(score_fn):
        raise InputTypeError(f"score_fn must be callable, got {describe(score_fn)}")
    if stop_fn is not None and not callable(stop_fn):
        raise InputTypeError(f"stop_fn must be callable or None, got {describe(stop_fn)}")
    x0, batched, sp = as_start(cm, start, start_pose, generator)
    B, D = x0.shape
    xy, heading = sp.xy.clone(), sp.heading.clone()  # (B, 2), (B,) the current root pose
    out = torch.empty(B, n_frames, D, dtype=torch.float32)  # normalized frames, CPU
    best_scores = torch.full((B, n_frames), float("nan"))
    done_at = torch.full((B,), -1, dtype=torch.long)
    # the current search: the characters searching, its best plan, the rows still committing
    # its frames and how many of them are left
    s = {"active": torch.arange(B), "left": 0}

    def search(f: int, cond: Tensor) -> None:
        """Propose P futures of H frames after frame f - 1 for the active characters; keep the
        best plan (its first ``commit`` frames, at most to the end)."""
        active = s["active"] = s["active"][done_at[s["active"]] < 0]
        b = active.numel()
        c = cond[active].repeat_interleave(P, dim=0)  # (b P, D), character-major

        def candidate(r: int) -> str:
            return f"character {int(active[r // P])}, candidate {r % P}"

        def propose(h: int, x: Tensor) -> Tensor:
            return cm.frame(x, generator)

        cand = autoregress(propose, c, H, first=f, who=candidate, desc="beam search")
        cand = cand.to(c.device, c.dtype).reshape(b, P, H, D)  # normalized
        future = Future(
            cm.denormalize(cand).float().cpu(), xy[active], heading[active], active, f - 1, cm.fps
        )
        scores = torch.as_tensor(score_fn(future)).to("cpu", torch.float64)
        if scores.shape != (b, P):
            raise ValueError(
                f"score_fn must return shape (b={b}, P={P}), got {tuple(scores.shape)}"
            )
        if torch.isnan(scores).any():
            raise ValueError(f"score_fn returned NaN at frame {f}")
        best = scores.argmax(dim=1)  # (b,)
        s["plan"] = cand[torch.arange(b), best.to(cand.device)]  # (b, H, D) normalized
        s["plan_feats"] = future.features[torch.arange(b), best]  # (b, H, D) feature units
        s["best_score"] = scores[torch.arange(b), best].float()
        s["going"] = torch.arange(b)  # rows of this search still committing frames
        s["j"], s["left"] = 0, min(commit, n_frames - f + 1)

    def step(f: int, cond: Tensor) -> Tensor:  # frame f (B, D): the best plan's next frame
        if s["left"] == 0:
            search(f, cond)
        j, going = s["j"], s["going"]
        rows = s["active"][going]
        x = cond.clone()  # characters that have stopped keep their state
        x[rows] = s["plan"][going, j]
        best_scores[rows, f - 1] = s["best_score"][going]
        now = Future(s["plan_feats"][going, j][:, None, None], xy[rows], heading[rows], rows,
                     f - 1, cm.fps)  # fmt: skip
        xy[rows], heading[rows] = now.root_xy[:, 0, 0], now.heading[:, 0, 0]
        if stop_fn is not None:
            stop = torch.as_tensor(stop_fn(now), dtype=torch.bool).cpu().reshape(-1)
            if stop.shape != (len(rows),):
                raise ValueError(
                    f"stop_fn must return shape (b={len(rows)},), got {tuple(stop.shape)}"
                )
            done_at[rows[stop]] = f
            s["going"] = going[~stop]
        s["j"], s["left"] = j + 1, s["left"] - 1
        return x

    def all_done(f: int) -> bool:  # every character has completed its task
        return s["left"] == 0 and bool((done_at[s["active"]] >= 0).all())

    frames = autoregress(
        step, cm.normalize(x0), n_frames, stop=all_done, desc="beam search", progress=progress
    )  # (B, f, D)
    out[:, : frames.shape[1]] = frames
    n_out = n_frames
    feats = cm.denormalize(out)
    for i in torch.nonzero(done_at >= 0)[:, 0].tolist():
        k = int(done_at[i])
        feats[i, k:] = _hold(feats[i, k - 1])
        out[i, k:] = cm.normalize(feats[i, k:])
    if not batched and done_at[0] >= 0:
        n_out = int(done_at[0])
    info = {"score": best_scores[:, :n_out], "done_at": done_at, "pool": P, "horizon": H,
            "commit": commit}  # fmt: skip
    if not batched:
        info = {**info, "score": info["score"][0], "done_at": int(done_at[0])}
    return Motion.from_normalized(cm, out[:, :n_out], sp, batched, info, features=feats[:, :n_out])


def _hold(frame: Tensor) -> Tensor:
    """``frame`` (D,) standing still: root velocity, yaw rate and joint velocities zeroed."""
    x = frame.clone()
    D = x.shape[-1]
    J = (D - 3) // 12
    x[:3] = 0
    x[3 + 3 * J : 3 + 6 * J] = 0
    return x
