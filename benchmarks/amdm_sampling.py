"""A-MDM sampling speed and long-rollout stability.

Prints JSON lines:

* ``speed``: ms per generated frame (all T denoising steps) for the shipped book model and for
  an untrained paper-size denoiser (10 x 1024, T = 40, 183-dim frames), at several batch sizes,
  eager PyTorch (A-MDM §7.3.2 reports 21 ms/frame at T = 40 on an RTX 4090);
* ``stability``: a 10,000-frame rollout of the book model (or of each ``--stability``
  checkpoint, in one run): no NaN, the bone-length error, the root height and the root's
  horizontal speed per 1,000-frame window, and the wall time.

    python benchmarks/amdm_sampling.py --out benchmarks/results/amdm_sampling.jsonl  # CPU, ~6 min
    python benchmarks/amdm_sampling.py --device cuda --batch 1 4096
    python benchmarks/amdm_sampling.py --only stability --stability amdm mvae runs/study/x
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from common import emit, hardware, sync

import minimdm
from minimdm.amdm import evaluation
from minimdm.amdm.models import DenoiserConfig, MLPDenoiser
from minimdm.checkpoint import load_checkpoint
from minimdm.diffusion import NoiseSchedule, ddpm_sample


@torch.no_grad()
def ms_per_frame(model, schedule, batch: int, device: str, frames: int = 5) -> float:
    """Wall time of one frame: T reverse steps of a batch, conditioned on the previous one."""
    D = model.config.x_dim
    g = torch.Generator(device=device).manual_seed(0)
    cond = torch.randn(batch, D, device=device, generator=g)
    ddpm_sample(
        model, schedule, (batch, D), cond=cond, generator=g, predicts=model.predicts
    )  # warm-up
    sync(device)
    t0 = time.perf_counter()
    for _ in range(frames):
        cond = ddpm_sample(
            model, schedule, (batch, D), cond=cond, generator=g, predicts=model.predicts
        )
    sync(device)
    return (time.perf_counter() - t0) / frames * 1e3


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--batch", type=int, nargs="+", default=[1, 64, 1024])
    p.add_argument("--frames", type=int, default=10_000, help="length of the stability rollout")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--skip-paper", action="store_true", help="skip the paper-size denoiser")
    p.add_argument("--out", default=None, help="append the lines to this .jsonl file")
    p.add_argument("--only", choices=["speed", "stability"], default=None)
    p.add_argument(
        "--stability",
        nargs="+",
        default=["amdm"],
        help="models of the stability rollout: shipped names (amdm, mvae, mse) or folders",
    )
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = args.device

    book = minimdm.pretrained("amdm", dev)  # the book's base model
    D = book.model.config.x_dim
    models = {"amdm": (book.model, book.schedule(dev))}
    if not args.skip_paper:
        torch.manual_seed(0)
        paper = MLPDenoiser(DenoiserConfig(D, D, 1024, 10, 128, "eps")).to(dev).eval()
        models["paper_10x1024_untrained"] = (paper, NoiseSchedule("cosine", 40, device=dev))
    for name, (model, schedule) in models.items() if args.only != "stability" else ():
        n_params = sum(p.numel() for p in model.parameters())
        for batch in args.batch:
            frames = 5 if batch * schedule.T * n_params < 5e11 else 2
            ms = ms_per_frame(model, schedule, batch, dev, frames)
            emit({"bench": "speed", "model": name, "params": n_params, "T": schedule.T,
                  "batch": batch, "ms_per_frame": round(ms, 2),
                  "character_frames_per_s": round(batch / ms * 1e3, 1),
                  "hardware": hardware(dev)}, args.out)  # fmt: skip

    for name in args.stability if args.only != "speed" else ():
        ckpt = (
            minimdm.pretrained(name, dev) if "/" not in name else load_checkpoint(name, device=dev)
        )
        state = evaluation.initial_state(ckpt, "dataset-1_walk_normal_001", 5)  # a held-out take
        t0 = time.perf_counter()
        d = evaluation.drift(
            ckpt, state, n_frames=args.frames, n_samples=4, window=1000, device=dev
        )
        seconds = time.perf_counter() - t0
        emit({"bench": "stability", "model": name, "frames": args.frames, "samples": 4,
              "seconds": round(seconds, 1), "ms_per_frame": round(seconds / args.frames * 1e3, 2),
              "finite": bool(all(np.isfinite(d[k]).all() for k in d)),
              "window_end": d["frame"].tolist(),
              "bone_err_cm": [round(float(x), 3) for x in d["bone_err"]],
              "root_height_m": [round(float(x), 3) for x in d["root_height"]],
              "root_speed_m_s": [round(float(x), 3) for x in d["root_speed"]],
              "hardware": hardware(dev)}, args.out)  # fmt: skip


if __name__ == "__main__":
    main()
