"""How strongly a base model answers a steering residual (A-MDM eq. 7), level by level.

For each denoising level t alone, a residual of 0.5 (standard deviations of the normalized
frame's feature; :class:`~minimdm.rl.env.ResidualSteerer`) on one root feature (forward speed,
sideways speed, yaw rate) is added after the step from t, and the next frame's change in that
feature is measured against the same draw without it, averaged over 64 training frames: the
gain per unit push at that level (1 at the last level, where nothing denoises after it). The
``authority`` of a residual schedule is the sum over its levels of w^t times the gain: how far
a unit action moves the next frame. The configs of chapter 7's policies use the 10 noisiest of
20 levels, w^t falling linearly from 2 to 0.2.

``--spin`` also measures whether the base model comes back from a turn: the yaw residual is held
at the box edge (+1) for 0.5, 1 or 2 s through that schedule, from frame 20 of the held-out
walk and run takes; then the model runs on alone for 7 s. It reports the share of characters
still spinning (heading turning faster than 180 degrees per second over half a second, as
``benchmarks/rl_joystick_study.py`` counts) 1, 3 and 7 s after the push. A base model that
keeps spinning on its own hands a policy a trap that no later action undoes quickly. With
``--max-yaw-rate L`` it measures the same pushes again behind the steerer's turn governor
(:class:`~minimdm.rl.env.ResidualSteerer`'s ``max_yaw_rate``), both in the same run, and
reports how far each push turned the character.

``--counter`` asks whether the residual can stop such a spin, and whether the spin stays
stopped: after the 1 s push, the yaw residual is held against the turn (at the box edge, the
sign opposite the current yaw rate) for 1 s, with the forward residual at 0, +1 or -1, and then
the model runs on alone for 5 s. It reports the share spinning at the end of the counter-push
and 1 and 5 s after it. Models are shipped names or checkpoint paths (a study's run).

    python benchmarks/rl_residual_gain.py amdm amdm_halting --spin \
        --out benchmarks/results/rl_residual_gain.jsonl
    python benchmarks/rl_residual_gain.py amdm --spin --max-yaw-rate 120 \
        --out benchmarks/results/rl_residual_gain.jsonl
    python benchmarks/rl_residual_gain.py amdm --counter \
        --out benchmarks/results/rl_residual_gain.jsonl
"""

from __future__ import annotations

import argparse
import itertools
import math

import torch
from common import emit, hardware  # noqa: I001  (benchmarks/common.py puts the repo on the path)
from rl_joystick_study import SPIN_DEG_S  # one threshold for "spinning" in both benchmarks

import minimdm
from minimdm.amdm import evaluation
from minimdm.amdm.sampling import Sampler
from minimdm.checkpoint import load_checkpoint
from minimdm.rl.env import ResidualSteerer
from minimdm.rl.residual import ResidualSchedule
from minimdm.rl.train import corpus_starts

FEATURES = ("forward", "sideways", "yaw")


@torch.no_grad()
def level_gains(cm: Sampler, starts: torch.Tensor, push: float = 0.5) -> dict[int, list[float]]:
    """``{level: [gain per feature]}`` for every level of the chain, noisiest first."""
    T, out = cm.schedule.T, {}
    for level in range(T - 1, -1, -1):
        steer = ResidualSteerer(cm, ResidualSchedule(T, (level,), "none", 1.0, tied=True), "root")
        row = []
        for f in range(len(FEATURES)):
            a = torch.zeros(len(starts), len(FEATURES))
            a[:, f] = push
            free = steer(starts, torch.zeros_like(a), torch.Generator().manual_seed(0))
            pushed = steer(starts, a, torch.Generator().manual_seed(0))
            row.append(float((pushed - free)[:, steer.idx[f]].mean()) / push)
        out[level] = row
    return out


@torch.no_grad()
def spin_after_push(
    cm: Sampler, starts: torch.Tensor, steer: ResidualSteerer, push_frames: int, after: int
) -> torch.Tensor:
    """(B, after) whether each character spins at each frame after a full yaw push held for
    ``push_frames`` frames, the model then running on with zero residuals; and (B,) the
    degrees each turned during the push."""
    a = torch.zeros(len(starts), len(FEATURES))
    a[:, FEATURES.index("yaw")] = 1.0
    yaw_col, gen, x = cm.layout.yaw_rate.start, torch.Generator().manual_seed(0), starts
    rates = []
    for f in range(push_frames + after):
        x = steer(x, a if f < push_frames else torch.zeros_like(a), gen)
        rates.append(cm.denormalize(x)[:, yaw_col])  # radians per frame
    deg_s = torch.stack(rates, 1) * cm.fps * 180 / math.pi
    smooth = torch.nn.functional.avg_pool1d(
        deg_s[:, push_frames:, None].transpose(1, 2), 15, 1, padding=7, count_include_pad=False
    )
    return smooth[:, 0].abs() > SPIN_DEG_S, deg_s[:, :push_frames].sum(1) / cm.fps


@torch.no_grad()
def counter_after_spin(
    cm: Sampler, starts: torch.Tensor, steer: ResidualSteerer, forward: float
) -> torch.Tensor:
    """(B, 7 s of frames) whether each character spins, frame by frame, over a full yaw push
    held for 1 s (as :func:`spin_after_push`), 1 s of counter-push and 5 s alone. The counter-push
    holds the yaw residual at the box edge against the current yaw rate and the forward
    residual at ``forward``."""
    yaw, fps = FEATURES.index("yaw"), round(cm.fps)
    yaw_col, gen, x = cm.layout.yaw_rate.start, torch.Generator().manual_seed(0), starts
    rates = []
    for f in range(fps + 6 * fps):
        a = torch.zeros(len(starts), len(FEATURES))
        if f < fps:  # the push that starts the spin
            a[:, yaw] = 1.0
        elif f < 2 * fps:  # against it
            a[:, yaw] = -torch.sign(cm.denormalize(x)[:, yaw_col])
            a[:, FEATURES.index("forward")] = forward
        x = steer(x, a, gen)
        rates.append(cm.denormalize(x)[:, yaw_col])
    deg_s = (torch.stack(rates, 1) * fps * 180 / math.pi).abs()
    smooth = torch.nn.functional.avg_pool1d(
        deg_s[:, :, None].transpose(1, 2), 15, 1, padding=7, count_include_pad=False
    )
    return smooth[:, 0] > SPIN_DEG_S


def load(name: str):
    """A shipped checkpoint by name, or one at a path."""
    return (
        load_checkpoint(name)
        if ("/" in name or name.endswith(".json"))
        else minimdm.pretrained(name)
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("models", nargs="+", help="base A-MDM checkpoints, e.g. amdm amdm_halting")
    p.add_argument("--levels", type=int, default=10, help="the schedule's noisiest levels")
    p.add_argument("--scale", type=float, default=2.0, help="the schedule's w at the top")
    p.add_argument("--spin", action="store_true", help="also: does it come back from a push?")
    p.add_argument(
        "--max-yaw-rate",
        type=float,
        default=None,
        help="--spin behind the turn governor at this many degrees per second",
    )
    p.add_argument(
        "--counter", action="store_true", help="also: does a counter-push stop a spin, for good?"
    )
    p.add_argument("--out", default=None, help="append the lines to this .jsonl file")
    args = p.parse_args()
    torch.set_num_threads(1)
    for name in args.models:
        ck = load(name)
        cm = Sampler.load(ck)
        starts = cm.normalize(corpus_starts(ck)[::400][:64])
        gains = level_gains(cm, starts)
        sched = ResidualSchedule.top(cm.schedule.T, args.levels, "linear", args.scale)
        w = dict(zip(sched.levels, sched.weights().tolist(), strict=True))
        authority = [sum(w[t] * gains[t][f] for t in sched.levels) for f in range(3)]
        emit({"bench": "residual_gain", "model": name, "features": list(FEATURES),
              "gain_by_level": {str(t): [round(g, 4) for g in v] for t, v in gains.items()},
              "schedule": sched.to_dict(),
              "authority": dict(zip(FEATURES, [round(a, 3) for a in authority], strict=True)),
              "hardware": hardware()}, args.out)  # fmt: skip
        if args.spin or args.counter:
            test = evaluation.checkpoint_clips(ck, split="test")
            takes = [c.name for c in test if c.labels["content"] in ("walk", "run")]
            held = cm.normalize(
                torch.stack([evaluation.initial_state(ck, n, 20).features for n in takes])
            ).repeat(4, 1)  # 4 futures per take
            tied = ResidualSchedule.top(cm.schedule.T, args.levels, "linear", args.scale, True)
        if args.counter:
            steer = ResidualSteerer(cm, tied, "root")
            for forward in (0.0, 1.0, -1.0):
                spinning = counter_after_spin(cm, held, steer, forward).float()
                fps = round(cm.fps)
                at = {  # label -> frame index
                    "spinning_after_push": fps - 1,
                    "spinning_end_of_counter": 2 * fps - 1,
                    "spinning_1s_after": 3 * fps - 1,
                    "spinning_5s_after": 7 * fps - 1,
                }
                emit({"bench": "counter_after_spin", "model": name,
                      "push": "yaw residual +1 (the box edge) for 1 s",
                      "counter": "yaw residual at the box edge against the yaw rate for 1 s",
                      "forward_during_counter": forward, "schedule": tied.to_dict(),
                      "starts": takes, "futures": len(held), "threshold_deg_s": SPIN_DEG_S,
                      **{k: round(float(spinning[:, f].mean()), 3) for k, f in at.items()},
                      "hardware": hardware()}, args.out)  # fmt: skip
        if args.spin:
            # the policies' schedule (tied: true), then behind the governor if asked
            governors = [None] + ([args.max_yaw_rate] if args.max_yaw_rate else [])
            for governor, seconds in itertools.product(governors, (0.0, 0.5, 1.0, 2.0)):
                steer = ResidualSteerer(cm, tied, "root", governor)  # 0 s: no push, the control
                spinning, turned = spin_after_push(cm, held, steer, round(seconds * cm.fps), 7 * 30)
                emit({"bench": "spin_after_push", "model": name, "push_s": seconds,
                      "push": "yaw residual +1 (the box edge)", "schedule": tied.to_dict(),
                      "max_yaw_rate": governor,
                      "turned_deg": round(float(turned.mean()), 1) if seconds else 0.0,
                      "starts": takes, "futures": len(held), "threshold_deg_s": SPIN_DEG_S,
                      **{f"spinning_{t}s": round(float(spinning[:, t * 30 - 1].float().mean()), 3)
                         for t in (1, 3, 7)},
                      "hardware": hardware()}, args.out)  # fmt: skip


if __name__ == "__main__":
    main()
