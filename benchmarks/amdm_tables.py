"""A-MDM §7.3 on the shipped checkpoints: Tables 1-4 and the scheduled-sampling ablation.

Prints one JSON line per row (config, hardware, metrics as mean and std over seeds, in cm):

* ``table1``: A-MDM (x0- and eps-prediction), MVAE-style and MSE from the same fixed initial
  states, plus the dataset;
* ``table2``: motion continuation from the last 30 frames of every clip;
* ``steps``: one model per T in {1, 2, 5, 10, 20, 40, 100} (``checkpoints/amdm_steps/T*``):
  APD, ADE, FS and ms/frame at batch 1, measured in the same run;
* ``drift``: bone error and root height over a 1,000-frame rollout with and without scheduled
  sampling (``amdm_eps_book`` vs ``amdm_eps_noss_book``; ``amdm_book`` for reference).

    python benchmarks/amdm_tables.py                 # the paper's protocol, ~15 min on 2 cores
    python benchmarks/amdm_tables.py --quick         # 4 states x 10 samples x 1 seed
    python benchmarks/amdm_tables.py --save benchmarks/results/amdm_tables.jsonl
"""

from __future__ import annotations

import argparse
import time

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
    p.add_argument("--only", nargs="+", choices=["table1", "table2", "steps", "drift"])
    p.add_argument("--device", default="cpu")
    p.add_argument("--save", help="also append the JSON lines to this file")
    args = p.parse_args()
    if args.quick:
        protocol = evaluation.Protocol(n_states=4, n_samples=10, seeds=(0,))
    else:
        protocol = evaluation.Protocol()  # 10 states x 50 samples, 150 frames, 3 seeds
    only = set(args.only or ["table1", "table2", "steps", "drift"])
    base = {"protocol": protocol.to_dict(), "hardware": hardware(args.device), "unit": "cm"}
    names = {
        "A-MDM": "amdm_book",
        "A-MDM (ε)": "amdm_eps_book",
        "MVAE-style": "mvae_book",
        "MSE": "mse_book",
    }
    models = {k: minimdm.pretrained(v, args.device) for k, v in names.items()}

    if "table1" in only:
        t0 = time.perf_counter()
        tab = evaluation.table1(models, protocol, with_dataset=True, device=args.device)
        for name, row in tab.items():
            ck = names.get(name, "dataset")
            emit({"table": "table1", "model": name, "checkpoint": ck, **base, **cells(row)},
                 args.save)  # fmt: skip
        print(evaluation.format_table(tab), f"\n({time.perf_counter() - t0:.0f} s)", flush=True)

    if "table2" in only:
        tab = evaluation.table2(models, protocol, device=args.device)
        for name, row in tab.items():
            emit({"table": "table2", "model": name, "checkpoint": names[name], **base,
                  **cells(row)}, args.save)  # fmt: skip
        print(evaluation.format_table(tab, evaluation.TABLE2_COLUMNS), flush=True)

    if "steps" in only:
        steps_models = {f"T={T}": minimdm.pretrained(f"amdm_steps/T{T}") for T in STEPS}
        tab = amdm_tables.steps_table(steps_models, protocol, device=args.device)
        for (_, row), T in zip(tab.items(), STEPS, strict=True):
            emit({"table": "steps", "T": T, "checkpoint": f"amdm_steps/T{T}", **base,
                  **cells(row)}, args.save)  # fmt: skip
        cols = ("APD", "ADE", "FS", "ms/frame")
        print(evaluation.format_table(tab, cols), flush=True)

    if "drift" in only:
        state = evaluation.initial_state(models["A-MDM"], "walker/0walk_forward", 20)
        for name in ("amdm_book", "amdm_eps_book", "amdm_eps_noss_book"):
            ck = minimdm.pretrained(name, args.device)
            d = evaluation.drift(ck, state, n_frames=1000, n_samples=8, device=args.device)
            emit({"table": "drift", "checkpoint": name, "start": "walker/0walk_forward:20",
                  **base, **{k: [round(float(x), 4) for x in v] for k, v in d.items()}},
                 args.save)  # fmt: skip


if __name__ == "__main__":
    main()
