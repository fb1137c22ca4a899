"""One-off migration: the shipped checkpoints clamp x0 to their training data's range.

Before issue 10 every x0 estimate was clamped to a symmetric box: ±5 normalized units for the
A-MDM checkpoints, ±6 for ``aamdm_book``, ±2 for the Squ-9 AAMDM. At ±5, 7.8% of the A-MDM
training frames have a feature outside the box (a chest rotation reaches 10σ), so jumps and
backflips could not be sampled. This script rebuilds each checkpoint's training data exactly as
its training did (the clips named in its metadata, normalized with its own statistics; for
AAMDM the standardised xz of its own autoencoder; for Squ-9 the study's seeded data), and
rewrites the metadata with :func:`minimdm.checkpoint.update_metadata` (weights bit-identical):

* A-MDM (``amdm_*``, ``amdm_steps/*``): ``diffusion.clip_x0`` becomes ``[[lo...], [hi...]]``.
  ``config.clip_x0`` keeps 5.0: it is what scheduled sampling clamped with while training.
* ``aamdm_book``: ``model.config.transition.clip_x0`` becomes the xz range; ``config.clip_x0``
  becomes ``"data"`` (the clamp never acts in AAMDM training, so the current config reproduces
  the weights).
* ``aamdm_squ9/aamdm``: ``model.config.clip_x0`` becomes the range of the study's training points
  (:meth:`Squ9Study.data_range`, what its ``build_aamdm`` now uses).

``mse_book`` and ``mvae_book`` do not clamp when sampling; they are left as they are. Each
migrated checkpoint records ``clip_x0_migration``. Run from the repository root:

    python benchmarks/migrate_clip_range.py          # prints one JSON line per checkpoint
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import load_file

from minimdm.aamdm.motion_train import checkpoint_training_xz
from minimdm.aamdm.train import GANConfig, PolishConfig
from minimdm.amdm.train import checkpoint_training_frames
from minimdm.checkpoint import load_checkpoint, update_metadata
from minimdm.diffusion import clamp_share, data_range
from minimdm.studies.squ9_acceleration import Squ9Study, Squ9StudyConfig

ROOT = Path(__file__).resolve().parents[1]
CKPT = ROOT / "checkpoints"
SCRIPT = "benchmarks/migrate_clip_range.py"


def _pair(frames) -> list[list[float]]:
    lo, hi = data_range(frames)
    return [lo.tolist(), hi.tolist()]


def _migrate(path: Path, edit, frames, old) -> dict:
    before = load_file(str(path.with_suffix(".safetensors")))
    update_metadata(path, edit)
    after = load_file(str(path.with_suffix(".safetensors")))
    same = before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)
    if not same:
        raise RuntimeError(f"{path}: the weights changed")
    ck = load_checkpoint(path)
    new = ck.metadata.get("diffusion", {}).get("clip_x0")
    if new is None:
        model = ck.model.transition if hasattr(ck.model, "transition") else ck.model
        new = model.config.clip_x0
    return {
        "checkpoint": path.relative_to(ROOT).as_posix(),
        "frames": int(frames.shape[0]),
        "share_outside_old": clamp_share(old, frames),
        "share_outside_new": clamp_share(new, frames),
    }


def migrate_amdm(path: Path) -> dict:
    ck = load_checkpoint(path)
    frames = checkpoint_training_frames(ck)  # (N, D) normalized, as in training
    old = ck.metadata["diffusion"]["clip_x0"]
    if not isinstance(old, (int, float)):
        old = ck.config.get("clip_x0")

    def edit(meta: dict) -> None:
        meta["diffusion"]["clip_x0"] = _pair(frames)
        meta["clip_x0_migration"] = {
            "from": old,
            "to": "the per-feature range of the normalized training frames",
            "script": SCRIPT,
            "note": f"trained with config.clip_x0 = {old} in scheduled sampling; the command's "
            "config now says clip_x0: data (add --set clip_x0=5.0 to retrain these weights "
            "bit for bit)",
        }

    return _migrate(path, edit, frames, old)


def migrate_aamdm_motion(path: Path) -> dict:
    ck = load_checkpoint(path)
    xz = checkpoint_training_xz(ck)  # (N, X + Z) standardised, as in training
    old = ck.model.transition.config.clip_x0

    def edit(meta: dict) -> None:
        meta["model"]["config"]["transition"]["clip_x0"] = _pair(xz)
        meta["config"]["clip_x0"] = "data"
        meta["clip_x0_migration"] = {
            "from": old,
            "to": "the per-feature range of the standardised xz training data",
            "script": SCRIPT,
        }

    return _migrate(path, edit, xz, old)


def migrate_squ9(path: Path) -> dict:
    ck = load_checkpoint(path)
    cfg = dict(ck.metadata["study_config"])
    cfg["gan"], cfg["polish"] = GANConfig(**cfg["gan"]), PolishConfig(**cfg["polish"])
    study = Squ9Study(Squ9StudyConfig(**cfg))  # the seeded data, no training
    points = torch.cat([study.x_prev, study.x_next, study.sequences.reshape(-1, 2)])
    old = ck.model.config.clip_x0

    def edit(meta: dict) -> None:
        lo, hi = study.data_range()
        meta["model"]["config"]["clip_x0"] = [lo.tolist(), hi.tolist()]
        meta["clip_x0_migration"] = {
            "from": old,
            "to": "the range of the study's training points",
            "script": SCRIPT,
        }

    return _migrate(path, edit, points, old)


def main() -> None:
    # It also migrated amdm_book, aamdm_book, amdm_eps_book, amdm_eps_noss_book and the
    # DeepMimic amdm_steps, since retired or retrained: the book's corpus models were trained
    # with the clamps their configs name, so only the Squ-9 AAMDM still carries this migration.
    print(json.dumps(migrate_squ9(CKPT / "aamdm_squ9" / "aamdm")), flush=True)


if __name__ == "__main__":
    main()
