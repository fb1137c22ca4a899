"""Rank joystick policies on the held-out commands of ``benchmarks/rl_steering.py``, per segment.

Each command segment (120 frames) is scored over its last 60 frames; a policy that settles
within a few degrees on most segments and loses the command on a few shows it here (the median
segment and the share of segments more than 15 degrees off), where the benchmark's mean mixes
the two. Appends one row per policy to ``benchmarks/results/rl_study.jsonl``.

``--controllers`` scores hand-written controllers instead, on the same commands, starts and
seeds: the benchmark's proportional controller and PD controllers (``k_turn``: a yaw residual
also against the current yaw rate), each behind the 10-level residual schedule the policies had
before and behind schedules with more authority over the chain (more levels, a larger scale);
the steerers have no turn governor. It asks whether
any controller on these residuals settles every command, or whether the misses are the base
model's (its spins). One row per controller and schedule.

    python benchmarks/rl_joystick_study.py rl_joystick runs/rl_study/joy_amdm_s1
    python benchmarks/rl_joystick_study.py --controllers
    python benchmarks/rl_joystick_study.py --controllers --base runs/study/r14_x0_lvl_draw4_40k

``--base`` puts the controllers on another base model (a checkpoint path, e.g. a run of
chapter 3's study), with the 10-level schedule only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math

import rl_steering as B
import torch
from common import ROOT, hardware

import minimdm
from minimdm.amdm import evaluation
from minimdm.amdm.sampling import Sampler
from minimdm.checkpoint import load_checkpoint
from minimdm.motion.skeleton import wrap_angle
from minimdm.rl import load_steering
from minimdm.rl.env import ResidualSteerer
from minimdm.rl.residual import ResidualSchedule
from minimdm.rl.rollout import steer
from minimdm.rl.train import corpus_starts

SPIN_DEG_S = 180.0
"""Degrees per second: a character whose heading turns faster than this, averaged over half a
second, spins. 1.0% of the training takes' half-second windows turn that fast."""


N, F, SEEDS = 8, 480, (0, 1, 2)
PROTOCOL_NOTE = "last 60 frames of each 120-frame command"
CONTROLLERS = [(2.0, 0.0, 1.0), (2.0, 0.5, 1.0), (1.0, 0.3, 1.0), (3.0, 1.0, 2.0)]
"""(k_heading, k_turn, k_speed): the benchmark's proportional controller, then PD ones."""
SCHEDULES = [(10, 2.0), (10, 3.0), (15, 2.0), (10, 4.0)]
"""(levels, scale) of the tied linear root residual: the 10 levels the policies had before
issue 31's fix first (the shipped joystick policy now uses 15, behind a governor)."""


def turn_seconds(he: torch.Tensor, fps: float, least: float = 45.0) -> torch.Tensor:
    """Seconds from each direction change of at least ``least`` degrees until the heading is
    first within 10 degrees of the new command (the whole 4 s segment if never); ``he`` is the
    absolute heading error in degrees, (N, F)."""
    out = []
    for k in range(1, he.shape[1] // 120):
        seg = he[:, k * 120 : (k + 1) * 120]
        for row in seg[seg[:, 0] >= least]:
            near = (row < 10).nonzero()
            out.append(float(near[0]) / fps if len(near) else seg.shape[1] / fps)
    return torch.tensor(out if out else [float("nan")])


def score(pol, starts, heading, speed, controller=None) -> list[dict]:
    """Per seed: the mean and median settled segment, the share of segments over 15 degrees,
    the settled speed error, the share of frames spinning, how fast the heading turns (the 99th
    percentile of its per-frame rate, degrees per second) and the median time to come round to a
    new direction (:func:`turn_seconds`)."""
    per_seed = []
    for seed in SEEDS:
        m = steer(
            pol,
            F,
            N,
            starts=starts,
            setup=lambda env: env.task.preset(heading, speed),
            seed=seed,
            controller=controller,
        )
        he = (m.info["heading_error"] * 180 / math.pi).abs()
        seg = torch.stack([he[:, k * 120 + 60 : (k + 1) * 120].mean(1) for k in range(4)], 1)
        sp = m.info["speed_error"].abs()[:, (torch.arange(F) % 120) >= 60]
        # spinning: the heading turns faster than SPIN_DEG_S, averaged over half a second
        rate = wrap_angle(torch.diff(m.heading, dim=1), include_pi=False)
        rate = rate * pol.cm.fps * 180 / math.pi
        turn = torch.nn.functional.avg_pool1d(rate[:, None], 15, 1)[:, 0]
        per_seed.append(
            {
                "settled_deg": float(seg.mean()),
                "median_segment_deg": float(seg.median()),
                "segments_over_15deg": float((seg > 15).float().mean()),
                "speed_err_settled_mps": float(sp.mean()),
                "spinning_share": float((turn.abs() > SPIN_DEG_S).float().mean()),
                "turn_rate_p99_deg_s": float(torch.quantile(rate.abs().flatten(), 0.99)),
                "turn_s": float(turn_seconds(he, pol.cm.fps).median()),
            }
        )
    return per_seed


SHOWN = (
    "settled_deg",
    "median_segment_deg",
    "segments_over_15deg",
    "speed_err_settled_mps",
    "spinning_share",
    "turn_rate_p99_deg_s",
    "turn_s",
)


def record(row: dict, per_seed: list[dict]) -> None:
    """Append ``row`` with the per-seed numbers and their means; print the means."""
    row = {
        **row,
        "per_seed": per_seed,
        **{k: round(sum(s[k] for s in per_seed) / len(per_seed), 3) for k in per_seed[0]},
        "hardware": hardware(),
    }
    with open(ROOT / "benchmarks" / "results" / "rl_study.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")
    shown = {k: row[k] for k in ("run", "controller", "schedule") if k in row}
    print(json.dumps({**shown, **{k: row[k] for k in SHOWN}}), flush=True)


def main() -> None:
    torch.set_num_threads(1)
    ck = minimdm.pretrained("amdm")
    test = evaluation.checkpoint_clips(ck, split="test")
    held = [c.name for c in test if c.labels["content"] in B.START_CONTENTS]
    starts = torch.stack([evaluation.initial_state(ck, n, 20).features for n in held])
    heading, speed = B.commands(N, F + 1, B.HELD_OUT_SEED)
    base_cm = Sampler.load(ck)
    yaw = corpus_starts(ck)[:, base_cm.layout.yaw_rate.start] * base_cm.fps * 180 / math.pi
    protocol = {
        # the training frames' own turning, for turn_rate_p99_deg_s
        "corpus_turn_rate_p99_deg_s": round(float(torch.quantile(yaw.abs(), 0.99)), 1),
        "commands": N,
        "frames": F,
        "starts": held,
        "held_out_seed": B.HELD_OUT_SEED,
        "seeds": list(SEEDS),
        "settled": PROTOCOL_NOTE,
    }
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="*", help="joystick policies: shipped names or run folders")
    p.add_argument("--controllers", action="store_true", help="score hand-written controllers")
    p.add_argument("--base", default=None, help="--controllers on this base model's checkpoint")
    args = p.parse_args()
    if args.controllers:
        pol = load_steering("rl_joystick")  # its base model, task and observation
        base, schedules = "amdm", SCHEDULES
        if args.base is not None:
            base, schedules = args.base, SCHEDULES[:1]
            pol = dataclasses.replace(pol, cm=Sampler.load(load_checkpoint(args.base)))
        T = pol.cm.schedule.T
        for levels, scale in schedules:
            sched = ResidualSchedule.top(T, levels, "linear", scale, tied=True)
            steering = dataclasses.replace(pol, steerer=ResidualSteerer(pol.cm, sched, "root"))
            for k_heading, k_turn, k_speed in CONTROLLERS:
                ctl = B.proportional_joystick(steering, k_heading, k_speed, k_turn)
                record(
                    {
                        "study": "hand-written joystick controllers (issue 31)",
                        "controller": {"k_heading": k_heading, "k_turn": k_turn,
                                       "k_speed": k_speed},
                        "schedule": sched.to_dict(),
                        "base": base,
                        "protocol": protocol,
                    },
                    score(steering, starts, heading, speed, ctl),
                )  # fmt: skip
        return
    for run in args.runs:
        pol = load_steering(run)
        meta = pol.checkpoint.metadata
        keys = (
            "residual_scale",
            "n_levels",
            "gamma",
            "total_steps",
            "max_turn_rate",
            "action_penalty",
            "max_yaw_rate",
        )
        record(
            {
                "study": "joystick on checkpoints/amdm (issue 31)",
                "run": run,
                "trained_as": meta.get("trained_as", meta["command"]),
                "config": {k: meta["config"][k] for k in keys if k in meta["config"]},
                "train_seconds": meta["train_seconds"],
                "final_reward_mean": meta["final_reward_mean"],
                "protocol": protocol,
            },
            score(pol, starts, heading, speed),
        )


if __name__ == "__main__":
    main()
