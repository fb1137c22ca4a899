"""How strongly a base model answers a steering residual (A-MDM eq. 7), level by level.

For each denoising level t alone, a residual of 0.5 (standard deviations of the normalized
frame's feature; :class:`~minimdm.rl.env.ResidualSteerer`) on one root feature (forward speed,
sideways speed, yaw rate) is added after the step from t, and the next frame's change in that
feature is measured against the same draw without it, averaged over 64 training frames: the
gain per unit push at that level (1 at the last level, where nothing denoises after it). The
``authority`` of a residual schedule is the sum over its levels of w^t times the gain: how far
a unit action moves the next frame. The configs of chapter 7's policies use the 10 noisiest of
20 levels, w^t falling linearly from 2 to 0.2.

    python benchmarks/rl_residual_gain.py amdm amdm_halting \
        --out benchmarks/results/rl_residual_gain.jsonl
"""

from __future__ import annotations

import argparse

import torch
from common import emit, hardware  # noqa: I001  (benchmarks/common.py puts the repo on the path)

import minimdm
from minimdm.amdm.sampling import Sampler
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("models", nargs="+", help="base A-MDM checkpoints, e.g. amdm amdm_halting")
    p.add_argument("--levels", type=int, default=10, help="the schedule's noisiest levels")
    p.add_argument("--scale", type=float, default=2.0, help="the schedule's w at the top")
    p.add_argument("--out", default=None, help="append the lines to this .jsonl file")
    args = p.parse_args()
    torch.set_num_threads(1)
    for name in args.models:
        ck = minimdm.pretrained(name)
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


if __name__ == "__main__":
    main()
