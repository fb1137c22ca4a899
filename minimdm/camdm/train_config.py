"""The training config of CAMDM (:mod:`minimdm.camdm.train`); ``configs/camdm*.yaml`` load into
it."""

from __future__ import annotations

import os
from dataclasses import dataclass

from minimdm import config as configs

from .model import CAMDMConfig

__all__ = ["CAMDMTrainConfig", "load_train_config"]


@dataclass
class CAMDMTrainConfig:
    """A CAMDM run; ``configs/camdm*.yaml`` load into it."""

    # ---- model (CAMDMConfig)
    latent: int = 256
    """Token width."""
    layers: int = 4
    """Transformer (or MLP) layers."""
    heads: int = 4
    """Attention heads."""
    ff: int = 1024
    """Feed-forward width (the width of an MLP backbone)."""
    dropout: float = 0.1
    """Transformer dropout."""
    tokens: str = "separate"
    """'separate' (SCT) or 'single' (the ablation w/o SCT)."""
    backbone: str = "transformer"
    """'transformer' or 'mlp' (the ablation w/ MLP)."""
    past: int = 10
    """P: past frames."""
    future: int = 45
    """F: future frames."""
    # ---- diffusion
    T: int = 8
    """Diffusion steps, in training and sampling (CAMDM: 8)."""
    schedule: str = "cosine"
    """Noise schedule."""
    # ---- losses (eq. 4) and condition dropout
    w_samp: float = 1.0
    """lambda_samp of eq. 4 (normalized units)."""
    w_pos: float = 1.0
    """lambda_pos: joint positions, metres (eq. 3)."""
    w_foot: float = 1.0
    """lambda_foot: foot velocity where the data's feet rest, metres per frame."""
    w_vel: float = 1.0
    """lambda_vel: joint velocities, metres per frame."""
    contact_speed: float = 0.01
    """A foot of the data rests when it moves less than this, metres per frame."""
    fk_scale: float = 10.0
    """The positions of eqs. 3-4 are measured in units of 1 / fk_scale metres (10: decimetres).
    The paper's x0 loss is on raw features (6D rotations, metres), ours on normalized ones, about
    100 times larger; decimetres give the geometric terms their weight against it with the
    paper's lambdas of 1 (in metres they were 1-5% of the loss and the motion jittered)."""
    p_drop_past: float = 0.15
    """Probability of replacing the past motion by the null (CFG-PM, eq. 5)."""
    p_drop_style: float = 0.0
    """Probability of replacing the style by the null style (CFG-S, the rejected variant)."""
    smooth_sigmas: list[float] | None = None
    """Gaussian widths (frames) the trajectory condition is smoothed with, one drawn per window
    (0: unsmoothed); None: [0, 0, 5, 10] as the official trainer."""
    # ---- optimisation
    lr: float = 1e-4
    """Adam learning rate after the warm-up."""
    lr_min: float = 1e-5
    """Learning rate at the end of the cosine decay."""
    warmup_steps: int = 200
    """Linear warm-up steps."""
    grad_clip: float = 1.0
    """Clip the gradient norm (0: no clipping)."""
    batch_size: int = 64
    """Windows per step."""
    total_steps: int = 10000
    """Optimizer steps."""
    style_balance: float = 0.0
    """How a batch's windows are drawn: a window counts (windows of its style)^-style_balance.
    0: every window equally likely, so a style counts by its length (in the training takes,
    sad has 10 times the windows of normal); 1: every style equally likely."""
    ema_decay: float = 0.999
    """EMA of the weights, sampled with (0: none)."""
    log_interval: int = 100
    """Append the running loss to log.jsonl every this many steps."""
    eval_interval: int = 1000
    """Held-in and held-out losses every this many steps (0: only at the end)."""
    ckpt_interval: int = 1000
    """Write a resumable checkpoint every this many steps (0: only at the end)."""
    seed: int = 0
    """Seeds the weights and every random draw."""
    # ---- data
    fps: float = 30.0
    """Frame rate (CAMDM: 30)."""
    corpus: str = "bandai-namco-1"
    """The corpus (:func:`minimdm.motion.corpora.load_motion`); its clips need style labels."""
    split: str | None = "train"
    """'train' takes of the fixed split (the test takes give the held-out loss), or None."""
    contents: list[str] | None = None
    """Only takes of these contents (None: the locomotion contents walk, run, dash, walk-back,
    walk-left, walk-right)."""
    mirror: bool = False
    """Also train on every take reflected left/right (:mod:`minimdm.motion.mirror`): twice the
    windows, and every turn in both directions. A take keeps its style; held-out takes are not
    mirrored."""
    device: str = "cpu"
    """'cpu' or 'cuda'."""
    config_file: str | None = None
    """The file this config came from (set by load_train_config)."""

    def __post_init__(self) -> None:
        self.model_config(1, 1)  # checks the model fields
        for name in ("T", "batch_size", "total_steps", "log_interval"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("p_drop_past", "p_drop_style"):
            if not 0 <= getattr(self, name) < 1:
                raise ValueError(f"{name} must lie in [0, 1), got {getattr(self, name)}")
        if not (0 <= self.style_balance <= 1):
            raise ValueError(f"style_balance must lie in [0, 1], got {self.style_balance}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must lie in [0, 1), got {self.ema_decay}")

    def model_config(self, dim: int, n_styles: int) -> CAMDMConfig:
        sizes = (self.past, self.future, self.latent, self.layers, self.heads, self.ff)
        return CAMDMConfig(dim, n_styles, *sizes, self.dropout, self.tokens, self.backbone)


def load_train_config(path: str | os.PathLike) -> CAMDMTrainConfig:
    """Read a YAML or TOML file into a :class:`CAMDMTrainConfig` (unknown keys are errors)."""
    return configs.load_config(path, CAMDMTrainConfig)
