"""Probe of the base-model study: the pace of one step drawn from the recording.

:func:`~minimdm.studies.locomotion.one_step_pace` draws every next frame of the held-out
locomotion takes from the recorded frames before it, and compares the draws' root speed with the
recording's. Set beside the yardstick's rollouts of the same run, it tells a model that learned
to speed up (or slow down) from one whose own frames lead it away. One JSON line per content and
one for all takes.

    python benchmarks/amdm_one_step.py runs/study/r11_h2_10k r11_h2_10k \\
        >> benchmarks/results/amdm_study_probes.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import torch
from common import hardware  # noqa: I001  (benchmarks/common.py puts the repo on the path)

from minimdm.checkpoint import load_checkpoint
from minimdm.studies.locomotion import one_step_pace


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("tag", help="a name for the rows (the study's run name)")
    ap.add_argument("--samples", type=int, default=4, help="draws per frame")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    ckpt = load_checkpoint(args.checkpoint)
    t0 = time.perf_counter()
    pace = one_step_pace(ckpt, n_samples=args.samples, seed=args.seed)
    seconds = round(time.perf_counter() - t0, 1)
    for scope, row in pace.items():
        print(
            json.dumps(
                {
                    "benchmark": "locomotion",
                    "probe": "one_step",
                    "checkpoint": args.checkpoint,
                    "tag": args.tag,
                    "step": ckpt.step,
                    "scope": scope,
                    "samples": args.samples,
                    "seed": args.seed,
                    "hardware": hardware(),
                    "seconds": seconds,
                }
                | row
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
