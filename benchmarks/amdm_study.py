"""The base-model study: train one A-MDM recipe, then score it on the locomotion yardstick.

Each call trains ``--base`` with the ``--set`` overrides into ``runs/study/NAME`` (resuming if
the folder holds a run), then runs ``minimdm.studies.locomotion`` on it and appends one row to
``benchmarks/results/amdm_study.jsonl``: the config, the training time, the held-out loss and
the yardstick's numbers for all takes and per content. Proxy runs rank the candidates; the
winner is trained at full length with ``minimdm train``. ``--table1`` scores the run on Table 1
(A-MDM §7.3, the full protocol: 10 held-out states x 50 futures x 3 seeds) instead, one row with
``"table1"`` in place of the yardstick, since APD, ADE and FDE are what the yardstick does not
rank.

    python benchmarks/amdm_study.py x0 --set predicts=x0 clip_x0=data --steps 10000

``--sampling-steps`` and ``--eta`` score a trained run with another sampler (DDIM, A-MDM §3.3)
under its own ``--label``, to tell what the sampler's noise does from what the network does.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path

import torch
import yaml
from common import ROOT, emit, hardware  # noqa: I001  (benchmarks/common.py puts the repo on the path)

from minimdm.amdm import evaluation
from minimdm.amdm.train import load_config, read_log, train_amdm
from minimdm.config import with_changes
from minimdm.studies.locomotion import LocomotionProtocol, locomotion_report

RESULTS = ROOT / "benchmarks" / "results" / "amdm_study.jsonl"


def _value(text: str):
    return yaml.safe_load(text)


def train_takes(names: list[str]) -> dict[str, int]:
    """Training takes per corpus and content, from Bandai-Namco take names
    (``dataset-1_walk_normal_001`` counts as ``dataset-1 walk``); other names count by name."""
    parts = [n.split("_") for n in names]
    return dict(Counter(f"{p[0]} {p[1]}" if len(p) == 4 else "_".join(p) for p in parts))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name", help="the run's name: runs/study/NAME")
    ap.add_argument("--base", default=str(ROOT / "configs" / "amdm.yaml"))
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    ap.add_argument("--steps", type=int, default=None, help="total_steps (a proxy's length)")
    ap.add_argument("--samples", type=int, default=4, help="futures per take")
    ap.add_argument("--long-seconds", type=float, default=60.0)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0], help="sampling seeds to score")
    ap.add_argument("--eval-only", action="store_true", help="score the run as it is")
    ap.add_argument("--table1", action="store_true", help="score on Table 1 instead")
    ap.add_argument("--sampling-steps", type=int, default=None, help="denoising steps (DDIM)")
    ap.add_argument("--eta", type=float, default=1.0, help="DDIM stochasticity, with those steps")
    ap.add_argument(
        "--cond-level",
        type=float,
        default=None,
        help="the condition noise a model told it (cond_level) assumes at run time",
    )
    ap.add_argument("--label", default=None, help="the row's name (default: the run's)")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    changes = dict(kv.split("=", 1) for kv in args.set)
    changes = {k: _value(v) for k, v in changes.items()}
    if args.steps is not None:
        changes["total_steps"] = args.steps
    config = with_changes(load_config(args.base), changes, where="--set")
    run = ROOT / "runs" / "study" / args.name
    t0 = time.perf_counter()
    if not args.eval_only:
        train_amdm(config, run, progress=False, num_threads=1)
    train_wall = time.perf_counter() - t0
    from minimdm.checkpoint import load_checkpoint

    ckpt = load_checkpoint(run)
    if args.eval_only:  # the run's own config, and what it changed from the base
        config = with_changes(config, ckpt.config, where=str(run))
        base = asdict(load_config(args.base))
        changes = {
            k: v for k, v in asdict(config).items() if base.get(k) != v and k != "config_file"
        }
    if args.cond_level is not None:  # the level a model told its condition's noise assumes
        if getattr(ckpt.model.config, "cond_level", None) is None:
            ap.error(f"--cond-level needs a model trained with cond_level; {run} has none")
        ckpt.model.config.cond_level = args.cond_level
    log = [rec for _, rec in read_log(run / "log.jsonl")]
    heldout = [r["heldout_loss"] for r in log if "heldout_loss" in r]
    head = {
        "benchmark": "amdm_study",
        "name": args.label or args.name,
        "base": Path(args.base).name,
        "changes": changes,
        "config": asdict(config),
        "step": ckpt.metadata.get("step"),
        "train_seconds": ckpt.metadata.get("train_seconds"),
        "train_wall_this_call": round(train_wall, 1),
        "heldout_loss": heldout[-1] if heldout else None,
        "heldout_loss_min": min(heldout) if heldout else None,
        "sampling_cond_level": getattr(ckpt.model.config, "cond_level", None),
        "train_takes": train_takes(ckpt.metadata.get("data", {}).get("clips") or []),
        "train_windows": ckpt.metadata.get("data", {}).get("windows"),
    }
    if args.table1:
        protocol = evaluation.Protocol()
        t1 = time.perf_counter()
        tab = evaluation.table1({args.name: ckpt}, protocol)[args.name]
        table = {k: {"mean": round(m, 4), "std": round(s, 4)} for k, (m, s) in tab.items()}
        emit({**head, "protocol": protocol.to_dict(), "eval_seconds":
              round(time.perf_counter() - t1, 1), "table1": table, "hardware": hardware()},
             args.out, quiet=True)  # fmt: skip
        print(json.dumps({"name": args.name, **{k: v["mean"] for k, v in table.items()}}))
        return 0
    for seed in args.seeds:
        p = LocomotionProtocol(
            n_samples=args.samples,
            long_seconds=args.long_seconds,
            seed=seed,
            steps=args.sampling_steps,
            eta=args.eta,
        )
        t1 = time.perf_counter()
        rep = locomotion_report(ckpt, p)
        row = {
            **head,
            "protocol": rep["protocol"],
            "eval_seconds": round(time.perf_counter() - t1, 1),
            "all": rep["all"],
            "contents": rep["contents"],
            "hardware": hardware(),
        }
        emit(row, args.out, quiet=True)
        a = rep["all"]
        keys = ("speed_ratio_10s", "worst_speed_ratio_10s", "along_ratio_10s", "speed_ratio_60s",
                "moving_60s", "at_box_60s", "FS_ratio", "Jnt.Accel_ratio", "Bone.Err",
                "APD")  # fmt: skip
        summary = {k: round(a[k], 3) for k in keys if k in a}
        by = {c: round(v["speed_ratio_10s"], 2) for c, v in rep["contents"].items()}
        print(json.dumps({"name": head["name"], "seed": seed, **summary, "by_content": by}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
