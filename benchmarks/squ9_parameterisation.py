"""Squ-9: the denoiser predicting the noise, the clean sample or the velocity (chapter 1).

Trains chapter 1's conditional DDPM (T = 20, 4 x 128, 2000 steps) once per parameterisation
and seed, and prints one JSON line per model: sample quality (coverage, precision, transition
TV), the largest sample, and the error of the clean estimate at every level next to the ideal
denoiser's. Not a test.

    python benchmarks/squ9_parameterisation.py --save benchmarks/results/squ9_parameterisation.jsonl
    python benchmarks/squ9_parameterisation.py --seeds 0 --T 5     # one seed, another T
"""

from __future__ import annotations

import argparse
import time

import torch
from common import emit, hardware

from minimdm.studies.squ9_parameterisation import PREDICTS, run_seed, to_json


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--T", type=int, default=20)
    p.add_argument("--predicts", nargs="+", default=list(PREDICTS), choices=PREDICTS)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("--save", default=None, help="append the JSON lines to this file")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    hw = hardware("cpu")
    for seed in args.seeds:
        t0 = time.perf_counter()
        rows = run_seed(seed, args.T, tuple(args.predicts))
        for r in rows:
            rec = {"study": "squ9_parameterisation", **to_json(r), "hardware": hw}
            rec["seed_wall_s"] = round(time.perf_counter() - t0, 1)
            emit(rec, args.save)


if __name__ == "__main__":
    main()
