"""A-MDM §7.3 on the shipped checkpoints: Tables 1-4, the memorisation probe and drift.

Prints one JSON line per row (config, hardware, metrics as mean and std over seeds, in cm):

* ``table1``: A-MDM (``checkpoints/amdm``), MVAE-style and MSE, all trained on
  the Bandai-Namco training takes, from the same fixed initial states drawn from the held-out
  test takes, plus those takes' own row (``dataset``);
* ``table2``: motion continuation from the last 30 frames of every held-out take;
* ``memorisation``: the distance of generated poses to the nearest training pose, next to the
  same distance for the held-out takes' poses (median, 90th percentile, share under 1 cm);
* ``steps``: one model per T in {1, 2, 5, 10, 20, 40, 100} (``checkpoints/amdm_steps/T*``,
  smaller models trained on the same takes with the recipe of ``configs/amdm_steps.yaml``),
  from the same held-out states: the Table 1 metrics and ms/frame at batch 1, in one run;
* ``drift``: bone error and root height over a 1,000-frame rollout of the base model.

    python benchmarks/amdm_tables.py                 # the paper's protocol, 3 seeds
    python benchmarks/amdm_tables.py --quick         # 4 states x 10 samples x 1 seed
    python benchmarks/amdm_tables.py --save benchmarks/results/amdm_tables.jsonl
"""

from __future__ import annotations

import argparse
import time

import torch
from common import emit, hardware

import minimdm
from minimdm.amdm import evaluation
from minimdm.studies import amdm_tables

STEPS = (1, 2, 5, 10, 20, 40, 100)


def cells(row: dict) -> dict:
    """``{metric: {"mean", "std"}}``; a plain number (ms/frame) gets std 0."""
    pairs = {k: v if isinstance(v, tuple) else (v, 0.0) for k, v in row.items()}
    return {k: {"mean": round(m, 4), "std": round(s, 4)} for k, (m, s) in pairs.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="a small protocol, for a smoke run")
    p.add_argument(
        "--only", nargs="+", choices=["table1", "table2", "memorisation", "steps", "drift"]
    )
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (small batches: 1)")
    p.add_argument("--save", help="also append the JSON lines to this file")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    if args.quick:
        protocol = evaluation.Protocol(n_states=4, n_samples=10, seeds=(0,))
    else:
        protocol = evaluation.Protocol()  # 10 states x 50 samples, 150 frames, 3 seeds
    only = set(args.only or ["table1", "table2", "memorisation", "steps", "drift"])
    base = {"protocol": protocol.to_dict(), "hardware": hardware(args.device), "unit": "cm"}
    names = {"A-MDM": "amdm", "MVAE-style": "mvae", "MSE": "mse"}
    models = {k: minimdm.pretrained(v, args.device) for k, v in names.items()}

    if "table1" in only:
        t0 = time.perf_counter()
        tab = evaluation.table1(models, protocol, with_dataset=True, device=args.device)
        for name, row in tab.items():
            ck = names.get(name, "held-out takes")
            emit({"table": "table1", "model": name, "checkpoint": ck, **base, **cells(row)},
                 args.save)  # fmt: skip
        print(evaluation.format_table(tab), f"\n({time.perf_counter() - t0:.0f} s)", flush=True)

    if "table2" in only:
        tab = evaluation.table2(models, protocol, device=args.device)
        for name, row in tab.items():
            emit({"table": "table2", "model": name, "checkpoint": names[name], **base,
                  **cells(row)}, args.save)  # fmt: skip
        print(evaluation.format_table(tab, evaluation.TABLE2_COLUMNS), flush=True)

    if "memorisation" in only:
        t0 = time.perf_counter()
        for name, ck in models.items():
            probe = evaluation.memorisation_probe(ck, protocol, device=args.device)
            for frames, row in probe.items():
                emit({"table": "memorisation", "model": name, "frames": frames,
                      "checkpoint": names[name], **base, **cells(row)}, args.save)  # fmt: skip
        print(f"memorisation ({time.perf_counter() - t0:.0f} s)", flush=True)

    if "steps" in only:
        steps_models = {f"T={T}": minimdm.pretrained(f"amdm_steps/T{T}") for T in STEPS}
        tab = amdm_tables.steps_table(steps_models, protocol, device=args.device)
        for (_, row), T in zip(tab.items(), STEPS, strict=True):
            emit({"table": "steps", "T": T, "checkpoint": f"amdm_steps/T{T}", **base,
                  **cells(row)}, args.save)  # fmt: skip
        cols = ("APD", "ADE", "FS", "ms/frame")
        print(evaluation.format_table(tab, cols), flush=True)

    if "drift" in only:
        take, frame = "dataset-1_walk_normal_001", 20  # a held-out take
        state = evaluation.initial_state(models["A-MDM"], take, frame)
        d = evaluation.drift(models["A-MDM"], state, n_frames=1000, n_samples=8, device=args.device)
        emit({"table": "drift", "checkpoint": "amdm", "start": f"{take}:{frame}", **base,
              **{k: [round(float(x), 4) for x in v] for k, v in d.items()}}, args.save)  # fmt: skip


if __name__ == "__main__":
    main()
