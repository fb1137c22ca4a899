"""Probe of the base-model study: the locomotion yardstick with noise correlated across frames.

Each frame's reverse chain takes its noise from a tape (:class:`~minimdm.diffusion.NoiseTape`);
frame f's tape is ``rho * tape_{f-1} + sqrt(1 - rho^2) * z_f``. Every draw is still N(0, I), so
the model sees the inputs it was trained on, but the noise that an x0-skip passes on to the
frame (``skip_sigma``) changes slowly from frame to frame instead of anew in every frame. At
``rho`` 0 it is the yardstick's own sampling (other draws of the same distribution).

This is a probe, not a method of the book: the library has no correlated-noise sampler, so the
script wraps ``Sampler.frame``. It prints one JSON line, the yardstick's "all" row.

    python benchmarks/amdm_noise_probe.py runs/study/x0_mirror_skip12_10k 0.6 skip12_ar0.6 \\
        >> benchmarks/results/amdm_study_probes.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import torch
from common import hardware  # noqa: I001  (benchmarks/common.py puts the repo on the path)

from minimdm.amdm import sampling
from minimdm.checkpoint import load_checkpoint
from minimdm.diffusion import NoiseTape
from minimdm.studies.locomotion import LocomotionProtocol, locomotion_report


def correlated_frames(rho: float) -> None:
    """Make every ``Sampler.frame`` drawn from a generator use AR(1) noise across frames."""
    plain = sampling.Sampler.frame
    last: dict[str, torch.Tensor] = {}

    def frame(self, cond, generator=None, **kw):
        if not isinstance(generator, torch.Generator) or kw:
            return plain(self, cond, generator, **kw)
        B, D = cond.shape
        z = torch.randn((B, D * (self.schedule.T + 1)), generator=generator)  # enough columns
        prev = last.get("tape")
        same = prev is not None and prev.shape == z.shape
        tape = rho * prev + math.sqrt(1 - rho * rho) * z if same else z
        last["tape"] = tape
        return plain(self, cond, NoiseTape(tape))

    sampling.Sampler.frame = frame


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("rho", type=float, help="correlation of a frame's noise with the last's")
    ap.add_argument("tag", help="a name for the row")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    correlated_frames(args.rho)
    p = LocomotionProtocol(n_samples=4, seconds=10.0, long_seconds=60.0, seed=args.seed)
    t0 = time.perf_counter()
    rep = locomotion_report(load_checkpoint(args.checkpoint), p)
    row = {
        "benchmark": "locomotion",
        "probe": "ar1_noise",
        "rho": args.rho,
        "checkpoint": args.checkpoint,
        "tag": args.tag,
        "scope": "all",
        "hardware": hardware(),
        "seconds": round(time.perf_counter() - t0, 1),
        "protocol": rep["protocol"],
    } | rep["all"]
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
