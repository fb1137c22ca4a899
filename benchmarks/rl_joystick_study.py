"""Rank joystick policies on the held-out commands of ``benchmarks/rl_steering.py``, per segment.

Each command segment (120 frames) is scored over its last 60 frames; a policy that settles
within a few degrees on most segments and loses the command on a few shows it here (the median
segment and the share of segments more than 15 degrees off), where the benchmark's mean mixes
the two. Appends one row per policy to ``benchmarks/results/rl_study.jsonl``.

    python benchmarks/rl_joystick_study.py rl_joystick runs/rl_study/joy_amdm_s1
"""

from __future__ import annotations

import json
import math
import sys

import rl_steering as B
import torch
from common import ROOT, hardware

import minimdm
from minimdm.amdm import evaluation
from minimdm.motion.skeleton import wrap_angle
from minimdm.rl import load_steering
from minimdm.rl.rollout import steer

SPIN_DEG_S = 180.0
"""Degrees per second: a character whose heading turns faster than this, averaged over half a
second, spins. 1.0% of the training takes' half-second windows turn that fast."""


def main() -> None:
    torch.set_num_threads(1)
    ck = minimdm.pretrained("amdm")
    test = evaluation.checkpoint_clips(ck, split="test")
    held = [c.name for c in test if c.labels["content"] in B.START_CONTENTS]
    starts = torch.stack([evaluation.initial_state(ck, n, 20).features for n in held])
    N, F = 8, 480
    heading, speed = B.commands(N, F + 1, B.HELD_OUT_SEED)
    for run in sys.argv[1:]:
        pol = load_steering(run)
        meta = pol.checkpoint.metadata
        per_seed = []
        for seed in (0, 1, 2):
            m = steer(
                pol,
                F,
                N,
                starts=starts,
                setup=lambda env: env.task.preset(heading, speed),
                seed=seed,
            )
            he = (m.info["heading_error"] * 180 / math.pi).abs()
            seg = torch.stack(
                [he[:, k * 120 + 60 : (k + 1) * 120].mean(1) for k in range(4)], 1
            )  # (N, 4)
            sp = m.info["speed_error"].abs()[:, (torch.arange(F) % 120) >= 60]
            # spinning: the heading turns faster than SPIN_DEG_S, averaged over half a second
            turn = wrap_angle(torch.diff(m.heading, dim=1), include_pi=False) * 30 * 180 / math.pi
            turn = torch.nn.functional.avg_pool1d(turn[:, None], 15, 1)[:, 0]
            per_seed.append(
                {
                    "settled_deg": float(seg.mean()),
                    "median_segment_deg": float(seg.median()),
                    "segments_over_15deg": float((seg > 15).float().mean()),
                    "speed_err_settled_mps": float(sp.mean()),
                    "spinning_share": float((turn.abs() > SPIN_DEG_S).float().mean()),
                }
            )
        row = {
            "study": "joystick on checkpoints/amdm (issue 31)",
            "run": run,
            "trained_as": meta.get("trained_as", meta["command"]),
            "config": {
                k: meta["config"][k]
                for k in (
                    "residual_scale",
                    "n_levels",
                    "gamma",
                    "total_steps",
                    "max_turn_rate",
                    "action_penalty",
                    "max_yaw_rate",
                )
                if k in meta["config"]
            },
            "train_seconds": meta["train_seconds"],
            "final_reward_mean": meta["final_reward_mean"],
            "protocol": {
                "commands": N,
                "frames": F,
                "starts": held,
                "held_out_seed": B.HELD_OUT_SEED,
                "seeds": [0, 1, 2],
                "settled": "last 60 frames of each 120-frame command",
            },
            "per_seed": per_seed,
            **{k: round(sum(s[k] for s in per_seed) / 3, 3) for k in per_seed[0]},
            "hardware": hardware(),
        }
        with open(ROOT / "benchmarks" / "results" / "rl_study.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")
        print(
            json.dumps(
                {
                    k: row[k]
                    for k in (
                        "run",
                        "settled_deg",
                        "median_segment_deg",
                        "segments_over_15deg",
                        "speed_err_settled_mps",
                        "spinning_share",
                    )
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
