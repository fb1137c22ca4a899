"""Motion: A-MDM at 5 steps (DDIM) and at its full T, against AAMDM (3 + 2), in one run.

AAMDM §4.1 (Table 1) on the data the AAMDM checkpoint was trained on: for the book's models
(``checkpoints/amdm`` and ``checkpoints/aamdm``, both trained on the Bandai-Namco training takes)
every method rolls out frame 10 of each held-out test take with the same seed (a DeepMimic
checkpoint starts from :data:`minimdm.aamdm.eval.INITIAL_CLIPS`); one JSON line per method:

    study, method, network_calls, APD, FS, Bone.Err, Jnt.Accel, DIV, FD, fps, rollout_s

then the held-out takes' own values (the target of FS, Jnt.Accel and DIV) and, with --guidance, the
root-direction control of §3.5 (eq. 13): heading tracking error with and without guidance.
``fps`` is frames per second for one character (batch 1, one CPU thread or the GPU). Not a test.

    python benchmarks/motion_acceleration.py                       # ~15 s on 1 CPU thread
    python benchmarks/motion_acceleration.py --guidance
    python benchmarks/motion_acceleration.py --amdm /tmp/amdm --aamdm checkpoints/aamdm
    python benchmarks/motion_acceleration.py --device cuda
"""

from __future__ import annotations

import argparse
import json
import sys

import torch
from common import hardware

from minimdm.aamdm.motion_train import AAMDMTrainConfig, load_motion_data
from minimdm.checkpoint import load_checkpoint
from minimdm.studies.aamdm_motion import dataset_quality, guidance_study, motion_comparison


def load_amdm(where: str, device: str):
    """``pretrained`` (minimdm.pretrained("amdm"), the book's base model) or a checkpoint path."""
    if where == "pretrained":
        import minimdm

        return minimdm.pretrained("amdm", device=device)
    return load_checkpoint(where, device=device)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--amdm", default="pretrained", help="A-MDM checkpoint ('pretrained': book)")
    p.add_argument("--aamdm", default="checkpoints/aamdm", help="AAMDM checkpoint folder")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    p.add_argument("--frames", type=int, default=120, help="frames per rollout")
    p.add_argument("--samples", type=int, default=8, help="futures per initial frame")
    p.add_argument("--fps-frames", type=int, default=60, help="frames timed for FPS")
    p.add_argument("--guidance", action="store_true", help="also the root-direction control")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch.cuda.is_available() is False")
    amdm = load_amdm(args.amdm, args.device)
    aamdm_ckpt = load_checkpoint(args.aamdm, device=args.device)
    aamdm = aamdm_ckpt.model
    data = load_motion_data(AAMDMTrainConfig(**_data_fields(aamdm_ckpt)))
    hw = hardware(args.device)
    rows, _ = motion_comparison(
        amdm, aamdm, data, args.frames, args.samples, seed=args.seed,
        fps_frames=args.fps_frames, device=args.device,
    )  # fmt: skip
    for r in rows:
        print(json.dumps({"study": "motion", **r, "hardware": hw}), flush=True)
    ref = {k: round(v, 3) for k, v in dataset_quality(data).items()}
    print(json.dumps({"study": "motion", "method": "dataset", **ref}), flush=True)
    if args.guidance:
        for r in guidance_study(aamdm, data, seed=args.seed, device=args.device):
            print(json.dumps({"study": "motion_guidance", **r}), flush=True)
    print("done", file=sys.stderr)


def _data_fields(ckpt) -> dict:
    """The data to start from: a corpus checkpoint's held-out takes, else its training clips."""
    cfg = ckpt.config
    fields = {"horizons": list(ckpt.model.config.horizons)}
    if cfg.get("split") == "train":
        fields.update(corpus=cfg["corpus"], split="test", loop_frames=None)
    return fields


if __name__ == "__main__":
    main()
