"""Squ-9: AAMDM (3 + 2) against DD-GAN alone, the polisher alone, MVAE, MSE, DDPM-5 and DDPM-200.

AAMDM §4.2 (Figure 3) and the ablations of §4.3 (Table 2). Trains every model on the same data
with fixed seeds (:class:`minimdm.studies.squ9_acceleration.Squ9Study`), samples one transition per
evaluation
condition and prints one JSON line per method:

    study, method, coverage, precision, transition_tv, network_calls, ms_per_step,
    ms_per_batch, speedup_vs_ddpm200, train_s, hardware

then (with --ablation) one line per (T_GAN, T_ADM) setting. The six-panel figure and the
table are written in the same run (--figure). Not a test.

    python benchmarks/squ9_acceleration.py --figure squ9.png            # ~2 min on 1 CPU thread
    python benchmarks/squ9_acceleration.py --ablation                     # ~4 min: + T_GAN, T_ADM
    python benchmarks/squ9_acceleration.py --quick                        # 1/10 budgets, ~30 s
    python benchmarks/squ9_acceleration.py --device cuda --ablation
    python benchmarks/squ9_acceleration.py --ablation --save checkpoints/aamdm_squ9  # the chapter
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import torch
from common import hardware

from minimdm.studies.report import plot_panels
from minimdm.studies.squ9_acceleration import Squ9Study, Squ9StudyConfig, with_budget
from minimdm.utils import format_table


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    p.add_argument("--quick", action="store_true", help="every training budget divided by 10")
    p.add_argument("--ablation", action="store_true", help="also T_GAN in 2 3 4 10, T_ADM 0-3")
    p.add_argument("--figure", default=None, help="write the six-panel figure here (.png)")
    p.add_argument("--save", default=None, help="save every trained model in this folder")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch.cuda.is_available() is False")
    cfg = Squ9StudyConfig(seed=args.seed)
    if args.quick:
        cfg = with_budget(cfg, 0.1)
    study = Squ9Study(cfg, args.device)
    t0 = time.perf_counter()
    study.train(progress=False)
    hw = hardware(args.device)
    rows, samples = study.evaluate()
    for r in rows:
        print(json.dumps({"study": "squ9", **r, "hardware": hw}), flush=True)
    print(format_table(rows, _KEYS[1:], digits=3, first=_KEYS[0]), file=sys.stderr)
    if args.figure:
        plot_panels(study.x_eval, samples, rows).savefig(args.figure, dpi=90)
    if args.ablation:
        abl, _ = study.ablation()
        for r in abl:
            print(json.dumps({"study": "squ9_ablation", **r, "hardware": hw}), flush=True)
        print(format_table(abl, digits=3, first="T_gan"), file=sys.stderr)
    if args.save:
        study.save(args.save)
    print(f"total {time.perf_counter() - t0:.0f} s", file=sys.stderr)


_KEYS = (
    "label",
    "coverage",
    "precision",
    "transition_tv",
    "network_calls",
    "ms_per_step",
    "speedup_vs_ddpm200",
    "train_s",
)

if __name__ == "__main__":
    main()
