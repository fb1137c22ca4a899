"""Squ-9: AAMDM (3 + 2) against DD-GAN alone, the polisher alone, MVAE, MSE, DDPM-5 and DDPM-200.

AAMDM §4.2 (Figure 3) and the ablations of §4.3 (Table 2). Trains every model on the same data
with fixed seeds (:class:`minimdm.studies.squ9_acceleration.Squ9Study`), samples one transition per
evaluation
condition and prints one JSON line per method:

    study, method, coverage, precision, transition_tv, network_calls, ms_per_step,
    ms_per_batch, speedup_vs_ddpm200, train_s, hardware

then (with --ablation) one line per (T_GAN, T_ADM) setting. The six-panel figure and the
table are written in the same run (--figure). Not a test.

With --pairs it runs only the comparison of AAMDM's two pair constructions
(:mod:`minimdm.studies.aamdm_variants`: Algorithm 1's, ``pairs="paper"``, against DD-GAN's,
``pairs="ddgan"``), both variants in the same run, for every seed: one line per (seed, variant)
(``"kind": "seed"``), then the mean ± std over seeds and the paired difference
(``"kind": "summary"``), each with the comparison's config and the hardware; --out writes
the same lines to a file (chapter 8 reads ``benchmarks/results/squ9_aamdm_pairs.jsonl``).

    python benchmarks/squ9_acceleration.py --figure squ9.png            # ~2 min on 1 CPU thread
    python benchmarks/squ9_acceleration.py --ablation                     # ~4 min: + T_GAN, T_ADM
    python benchmarks/squ9_acceleration.py --quick                        # 1/10 budgets, ~30 s
    python benchmarks/squ9_acceleration.py --device cuda --ablation
    python benchmarks/squ9_acceleration.py --ablation --save checkpoints/aamdm_squ9  # the chapter
    python benchmarks/squ9_acceleration.py --pairs --out benchmarks/results/squ9_aamdm_pairs.jsonl
                                                   # ~5 min: 3 seeds x (polisher + 2 generators)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from dataclasses import asdict, replace

import torch
from common import emit, hardware

from minimdm.files import atomic_output, atomic_write
from minimdm.studies.aamdm_variants import METRICS, VariantsConfig, compare_pairs, summarize
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
    p.add_argument("--pairs", action="store_true", help="only: Algorithm 1's pairs vs DD-GAN's")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="--pairs seeds")
    p.add_argument("--gan-steps", type=int, default=1500, help="--pairs: GAN steps per variant")
    p.add_argument("--polish-steps", type=int, default=300, help="--pairs: polisher steps")
    p.add_argument("--out", default=None, help="--pairs: also write the JSON lines here")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch.cuda.is_available() is False")
    if args.pairs:
        pairs(args)
        return
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
        with atomic_output(args.figure) as tmp:
            plot_panels(study.x_eval, samples, rows).savefig(tmp, dpi=90)
    if args.ablation:
        abl, _ = study.ablation()
        for r in abl:
            print(json.dumps({"study": "squ9_ablation", **r, "hardware": hw}), flush=True)
        print(format_table(abl, digits=3, first="T_gan"), file=sys.stderr)
    if args.save:
        study.save(args.save)
    print(f"total {time.perf_counter() - t0:.0f} s", file=sys.stderr)


def pairs(args) -> None:
    """Both pair constructions, every seed, in this one run; JSON lines and a table."""
    t0 = time.perf_counter()
    cfg = VariantsConfig(
        seeds=tuple(args.seeds), gan_steps=args.gan_steps, polish_steps=args.polish_steps
    )
    if args.quick:
        cfg = replace(
            cfg, gan_steps=max(1, cfg.gan_steps // 10), polish_steps=max(1, cfg.polish_steps // 10)
        )
    with contextlib.redirect_stdout(sys.stderr):  # progress on stderr, JSON on stdout
        rows = compare_pairs(cfg, args.device, progress=True)
    hw = hardware(args.device)
    conf = {k: v for k, v in asdict(cfg).items() if k != "study"}
    conf["study"] = {k: v for k, v in asdict(cfg.study).items() if k not in ("gan", "polish")}
    conf["gan"], conf["polish"] = asdict(cfg.study.gan), asdict(cfg.study.polish)
    conf["gan"]["steps"], conf["polish"]["steps"] = cfg.gan_steps, cfg.polish_steps
    out = None
    if args.out:
        out = atomic_write(args.out, "")  # a fresh file, then one appended line per record
    base = {"study": "squ9_aamdm_pairs", "config": conf, "hardware": hw}
    for r in rows:
        emit({**base, "kind": "seed", **r}, out)
    summary = summarize(rows)
    for r in summary:
        stats = {m: {"mean": r[m][0], "std": r[m][1]} for m in METRICS}
        emit({**base, "kind": "summary", **{k: r[k] for k in ("model", "variant", "n_seeds")},
              **stats}, out)  # fmt: skip
    print(format_table(summary, ["n_seeds", *METRICS], digits=3), file=sys.stderr)
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
