"""Squ-9 quality and speed against the number of diffusion steps T (AAMDM §4.2, Figure 3).

Trains one conditional DDPM per T on the same Squ-9 pairs with a fixed seed, samples one
transition per evaluation pair, and prints one JSON line per T:

    config, hardware, coverage, precision, transition_tv, ms_per_step, ms_per_sample_batch

then one line for the deterministic MSE regressor (the one-to-one baseline). Not a test.

    python benchmarks/squ9_steps.py                  # T in 1 2 5 10 20 50 100, CPU
    python benchmarks/squ9_steps.py --quick          # fewer steps and T values, ~30 s
    python benchmarks/squ9_steps.py --device cuda --T 5 40 200 --steps 4000
    python benchmarks/squ9_steps.py --T 5 20 100 --seeds 0 1 2 --threads 1 \\
        --save benchmarks/results/squ9_steps.jsonl     # chapter 1's table, 3 seeds
"""

from __future__ import annotations

import argparse
import time

import torch
from common import emit, hardware, sync

from minimdm.amdm.models import DenoiserConfig, MLPDenoiser, MLPRegressor
from minimdm.diffusion import NoiseSchedule, ddpm_sample
from minimdm.toy.squ9 import Squ9, squ9_metrics, train_denoiser, train_regressor


def quality(sq: Squ9, x_eval: torch.Tensor, x_gen: torch.Tensor) -> dict:
    m = squ9_metrics(x_eval, x_gen, sq)
    return {k: round(m[k], 4) for k in ("coverage", "precision", "transition_tv")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--T", type=int, nargs="+", default=[1, 2, 5, 10, 20, 50, 100])
    p.add_argument("--kind", default="cosine", choices=["cosine", "linear"])
    p.add_argument("--steps", type=int, default=2000, help="training steps per model")
    p.add_argument("--batch-size", type=int, default=512)
    p.add_argument("--lr", type=float, default=3e-3)
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--depth", type=int, default=4)
    p.add_argument("--n-train", type=int, default=20_000)
    p.add_argument("--n-eval", type=int, default=4000)
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="one run per seed")
    p.add_argument("--save", default=None, help="append the JSON lines to this file")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--quick", action="store_true", help="T in 1 5 20, 500 steps")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = p.parse_args()
    for seed in args.seeds:
        args.seed = seed
        run(args)


def run(args: argparse.Namespace) -> None:
    """Every T and the regressor for one seed (data, weights, batches and sampling noise)."""
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.quick:
        args.T, args.steps = [1, 5, 20], 500
    dev = args.device
    if dev == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch.cuda.is_available() is False")

    sq = Squ9()
    x_prev, x_next = sq.sample_pairs(args.n_train, torch.Generator().manual_seed(args.seed))
    x_eval, _ = sq.sample_pairs(args.n_eval, torch.Generator().manual_seed(args.seed + 1))
    x_eval = x_eval.to(dev)
    hw = hardware(dev)
    common = {
        "kind": args.kind,
        "train_steps": args.steps,
        "batch_size": args.batch_size,
        "lr": args.lr,
        "width": args.width,
        "depth": args.depth,
        "n_train": args.n_train,
        "n_eval": args.n_eval,
        "seed": args.seed,
    }

    for T in args.T:
        torch.manual_seed(args.seed)
        model = MLPDenoiser(DenoiserConfig(2, 2, args.width, args.depth, time_dim=32)).to(dev)
        schedule = NoiseSchedule(args.kind, T, device=dev)
        g = torch.Generator(dev).manual_seed(args.seed)
        t0 = time.perf_counter()
        losses = train_denoiser(
            model, schedule, x_prev, x_next, args.steps, args.batch_size, args.lr, g
        )
        train_s = time.perf_counter() - t0
        warm = torch.Generator(dev).manual_seed(args.seed)
        ddpm_sample(model, schedule, (8, 2), cond=x_eval[:8], generator=warm)
        sync(dev)
        g = torch.Generator(dev).manual_seed(args.seed + 2)  # the draws of chapter 1
        t0 = time.perf_counter()
        x_gen = ddpm_sample(model, schedule, x_eval.shape, cond=x_eval, generator=g)
        sync(dev)
        sample_s = time.perf_counter() - t0
        row = {
            "model": "ddpm",
            "T": T,
            **common,
            "hardware": hw,
            **quality(sq, x_eval, x_gen),
            "final_loss": round(sum(losses[-100:]) / len(losses[-100:]), 4),
            "train_s": round(train_s, 2),
            "ms_per_step": round(1000 * sample_s / T, 3),
            "ms_per_sample_batch": round(1000 * sample_s, 2),
        }
        emit(row, args.save)

    torch.manual_seed(args.seed)
    reg = MLPRegressor(2, 2, args.width, args.depth).to(dev)
    g = torch.Generator(dev).manual_seed(args.seed)
    t0 = time.perf_counter()
    losses = train_regressor(reg, x_prev, x_next, args.steps, args.batch_size, args.lr, g)
    train_s = time.perf_counter() - t0
    with torch.no_grad():
        reg(x_eval[:8])
        sync(dev)
        t0 = time.perf_counter()
        x_gen = reg(x_eval)
        sync(dev)
        sample_s = time.perf_counter() - t0
    row = {
        "model": "mse_regressor",
        "T": None,
        **common,
        "hardware": hw,
        **quality(sq, x_eval, x_gen),
        "final_loss": round(sum(losses[-100:]) / len(losses[-100:]), 4),
        "train_s": round(train_s, 2),
        "ms_per_step": round(1000 * sample_s, 3),
        "ms_per_sample_batch": round(1000 * sample_s, 2),
    }
    emit(row, args.save)


if __name__ == "__main__":
    main()
