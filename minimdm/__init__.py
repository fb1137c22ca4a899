"""minimdm: auto-regressive motion diffusion, from DDPM to A-MDM, AAMDM and CAMDM.

The two names most readers need first::

    import minimdm
    ckpt = minimdm.pretrained("amdm")               # the book's A-MDM, trained on the corpus
    motion = minimdm.rollout(ckpt, x0, n_frames=300)  # sample the future of initial states x0
"""

from __future__ import annotations

import os
from pathlib import Path

from minimdm._version import __version__

__all__ = ["__version__", "pretrained", "rollout", "CHECKPOINT_DIR"]

CHECKPOINT_DIR = Path(
    os.environ.get("MINIMDM_CHECKPOINTS", Path(__file__).resolve().parent.parent / "checkpoints")
)
"""Where :func:`pretrained` looks: ``$MINIMDM_CHECKPOINTS`` or the checkout's ``checkpoints/``."""


def pretrained(name: str, device: str = "cpu"):
    """Load a shipped checkpoint by name, e.g. ``"amdm"`` or ``"amdm_steps/T5"``.

    Each lives in ``checkpoints/<name>/`` and records the command that made it in its metadata
    (``checkpoint.metadata["command"]``).
    """
    from minimdm.checkpoint import load_checkpoint

    folder = CHECKPOINT_DIR / name
    if not (folder / "model.safetensors").exists():
        have = sorted(
            p.parent.relative_to(CHECKPOINT_DIR).as_posix()
            for p in CHECKPOINT_DIR.glob("**/model.safetensors")
        )
        raise FileNotFoundError(
            f"no shipped checkpoint named {name!r} in {CHECKPOINT_DIR}; available: {have}. "
            f"{_make_hint(name)}"
        )
    return load_checkpoint(folder, device=device)


def _make_hint(name: str) -> str:
    """How to make a missing checkpoint, when a config of that name says so."""
    config = CHECKPOINT_DIR.parent / "configs" / f"{name}.yaml"
    if not config.exists():
        return "Each shipped checkpoint's metadata names the command that made it."
    trainer = "python -m minimdm.aamdm train" if name.startswith("aamdm") else "minimdm train"
    trainer = "minimdm rl" if name.startswith("rl_") else trainer
    if name.startswith("camdm"):
        trainer = "minimdm camdm classifier" if "classifier" in name else "minimdm camdm train"
    return f"Make it with: {trainer} configs/{name}.yaml --ship"


def __getattr__(name: str):
    if name == "rollout":  # imported lazily: `import minimdm` stays light
        from minimdm.amdm.sampling import rollout

        return rollout
    raise AttributeError(f"module 'minimdm' has no attribute {name!r}")
