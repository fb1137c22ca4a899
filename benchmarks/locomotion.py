"""Does a motion model keep moving like the data? (the yardstick of the base-model study)

From frame 45 of every held-out locomotion take of the corpus, each checkpoint draws futures of
60 s; prints one JSON line per take, per content and for all takes (``minimdm.studies.locomotion``
documents every number), plus the data's own row. Any motion checkpoint runs: A-MDM, the
MVAE-style and MSE baselines, AAMDM.

    python benchmarks/locomotion.py checkpoints/amdm checkpoints/mvae
    python benchmarks/locomotion.py runs/x --samples 2 --long-seconds 0 --takes
    python benchmarks/locomotion.py runs/x --split train   # held-in takes: pace or generalisation?
"""

from __future__ import annotations

import argparse
import sys
import time

import torch
from common import emit, hardware  # noqa: I001  (benchmarks/common.py puts the repo on the path)

from minimdm.checkpoint import load_checkpoint
from minimdm.studies.locomotion import LocomotionProtocol, locomotion_report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+", help="checkpoint folders")
    ap.add_argument("--samples", type=int, default=4, help="futures per take (default 4)")
    ap.add_argument("--seconds", type=float, default=10.0, help="the scored rollout (10 s)")
    ap.add_argument("--long-seconds", type=float, default=60.0, help="staying power (60 s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=None, help="denoising steps (default: T)")
    ap.add_argument("--eta", type=float, default=1.0, help="DDIM stochasticity with --steps")
    ap.add_argument("--corpus", default=None, help="labelled corpus (default: the checkpoint's)")
    ap.add_argument(
        "--split",
        default="test",
        choices=("test", "train"),
        help="start from the held-out takes (the yardstick) or the training takes (diagnostic)",
    )
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--takes", action="store_true", help="also print one line per take")
    ap.add_argument("--out", default=None, help="append the lines to this .jsonl file")
    ap.add_argument("--tag", default=None, help="a name for the rows (e.g. the study's run)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    p = LocomotionProtocol(
        n_samples=args.samples,
        seconds=args.seconds,
        long_seconds=args.long_seconds,
        seed=args.seed,
        steps=args.steps,
        eta=args.eta,
        corpus=args.corpus,
        split=args.split,
    )
    hw = hardware()
    for path in args.checkpoints:
        t0 = time.perf_counter()
        ckpt = load_checkpoint(path)
        rep = locomotion_report(ckpt, p)
        base = {
            "benchmark": "locomotion",
            "checkpoint": path,
            "tag": args.tag,
            "kind": rep["kind"],
            "step": ckpt.metadata.get("step"),
            "train_seconds": ckpt.metadata.get("train_seconds"),
            "protocol": rep["protocol"],
            "hardware": hw,
        }
        if args.takes:
            for row in rep["takes"]:
                emit(base | {"scope": "take"} | row, args.out)
        for content, row in rep["contents"].items():
            emit(base | {"scope": "content", "content": content} | row, args.out)
        all_ = {"scope": "all", "seconds": round(time.perf_counter() - t0, 1)} | rep["all"]
        emit(base | all_, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
