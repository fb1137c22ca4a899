"""The training config of A-MDM and its baselines, and what follows from it alone."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from torch import Tensor, nn

from minimdm import config as configs
from minimdm.amdm.losses import MODEL_KINDS
from minimdm.amdm.models import (
    MVAE,
    DenoiserConfig,
    MLPDenoiser,
    MLPRegressor,
    MVAEConfig,
    skip_weights,
)
from minimdm.nn import cosine_lr

SKIP_FEATURES = ("all", "root")
DELTA_FEATURES = ("all", "root", "not_positions", "joint_motion", "rotations")

__all__ = [
    "TrainConfig",
    "load_config",
    "student_probability",
    "learning_rate",
    "build_network",
    "motion_mask",
]


@dataclass
class TrainConfig:
    """Everything that defines a training run; ``configs/*.yaml`` load into it."""

    # ---- model
    model_kind: str = "amdm"
    """Which model: 'amdm' (diffusion), 'mse' (deterministic regressor) or 'mvae' (cond. VAE)."""
    width: int = 512
    """Hidden units per layer (A-MDM paper: 1024)."""
    depth: int = 6
    """Fully connected layers including the output layer (A-MDM paper: 10)."""
    time_dim: int = 128
    """Size of the sinusoidal diffusion-step embedding (amdm only)."""
    latent_dim: int = 32
    """Size of the MVAE latent z (mvae only)."""
    # ---- diffusion
    T: int = 40
    """Number of diffusion steps (A-MDM paper: 40)."""
    schedule: str = "cosine"
    """Noise schedule: 'cosine', 'linear' or 'karras' (see
    :class:`~minimdm.diffusion.NoiseSchedule`)."""
    predicts: str = "eps"
    """What the denoiser outputs: 'eps' (A-MDM eq. 3), 'x0' or 'v'."""
    skip_sigma: float = 0.0
    """x0 only: add the noisy frame to the output with the weight that is best for a next frame
    spread by this much around its mean (:func:`~minimdm.amdm.models.skip_weights`; normalized
    units); 0: no skip."""
    skip_features: str = "all"
    """Which features the skip passes on: 'all', or 'root' (the root's planar and yaw velocity,
    A-MDM's d_x, d_y, d_r). The noise a skip lets through is new in every frame: on the root's
    velocity it is integrated into a smooth path, on the joints it is jitter."""
    skip_sigma_root: float | None = None
    """x0 only: the skip's spread for the root's three velocity features (d_x, d_y, d_r) alone,
    whose next frame is the least predictable (the yaw rate most); None: ``skip_sigma``."""
    skip_sigma_yaw: float | None = None
    """x0 only: the skip's spread for the yaw rate d_r alone, after ``skip_sigma_root``: the
    turning choice, without the sideways and forward noise that slides the planted feet."""
    # ---- optimisation
    lr: float = 3e-4
    """Adam learning rate at the start."""
    lr_min: float = 3e-5
    """Learning rate at the end of a cosine decay over total_steps (= lr: constant)."""
    grad_clip: float = 1.0
    """Clip the gradient norm to this value (0: no clipping)."""
    batch_size: int = 128
    """Windows per step."""
    total_steps: int = 2000
    """Optimizer steps in the whole run."""
    kl_beta: float = 0.2
    """Weight of the KL term per frame dimension (mvae only)."""
    # ---- scheduled sampling (A-MDM §3.2, MVAE-style)
    rollout: int = 4
    """N_r: frames predicted per window, each conditioned on the previous one."""
    history: int = 1
    """How many previous frames condition the next one: 1, the paper's :math:`x_{f-1}`; H > 1
    gives the network :math:`[x_{f-H}, \\dots, x_{f-1}]` (:attr:`DenoiserConfig.history`), and
    each training window holds H - 1 more recorded frames before the N_r it predicts."""
    teacher_steps: int = 500
    """Steps of pure teacher forcing (student probability 0)."""
    ramp_steps: int = 500
    """Steps over which the student probability rises linearly from 0 to 1."""
    student_steps: int = 0
    """What a student step feeds back: 0, the reconstruction at the loss's noise level (A-MDM
    §3.2); k >= 1, a frame drawn by the reverse chain over k steps (T: DDPM, fewer: DDIM), as
    the sampler draws it at run time (amdm only; costs k network calls per fed-back frame)."""
    teacher_weight: float = 0.0
    """Weight of a teacher-forced loss added while the student probability is above 0, as in
    the official A-MDM trainer (student loss + teacher loss at every rollout step); 0: none."""
    norm: str = "l2"
    """The DDPM loss's error: 'l2' (squared, eq. 3) or 'l1' (absolute, the official code's)."""
    snr_gamma: float | None = None
    """Weight the training loss's noise levels by Min-SNR-γ (Hang et al. 2023; amdm only): as an
    error on the clean frame, level t counts min(SNR_t, γ); None: the loss of ``predicts`` as is
    (the held-out loss stays unweighted)."""
    snr_floor: float = 0.0
    """With ``snr_gamma``: the noisiest levels count at least this much (1: as in the x0 loss;
    Min-SNR itself gives them nearly 0)."""
    geo_consistency: float = 0.0
    """Weight of the loss that makes a predicted frame's root, positions and displacements agree
    (amdm only; :class:`~minimdm.amdm.losses.FrameGeometry`); 0: none."""
    geo_contact: float = 0.0
    """Weight of the loss that keeps the feet still where the recording plants them (amdm only;
    :class:`~minimdm.amdm.losses.FrameGeometry`); 0: none."""
    geo_bones: float = 0.0
    """Weight of the loss that keeps a predicted frame's bone lengths those of the recording
    (amdm only; :class:`~minimdm.amdm.losses.FrameGeometry`); 0: none."""
    delta: bool = False
    """Denoise the change from the previous frame instead of the frame (amdm only):
    :math:`z_f = (x_f - x_{f-1}) / k` with :math:`k` each feature's spread of that change in the
    training windows (:meth:`~minimdm.amdm.models.MLPDenoiser.to_delta`)."""
    delta_features: str = "all"
    """Which features a ``delta`` model denoises as a change: 'all'; 'root' (the root's
    velocity and yaw rate d_x, d_y, d_r; the joints are denoised as they are); or
    'not_positions' (all but the joint positions j_p, which are denoised as they are, so that
    their errors do not add up from frame to frame); or 'joint_motion' (only the joints'
    velocities and rotations j_v, j_o: the root's motion and the joint positions are denoised
    as they are); or 'rotations' (only the joint rotations j_o: every position and velocity,
    and with them the pace, is denoised as it is)."""
    cond_noise: float = 0.0
    """Spread of Gaussian noise added to the condition :math:`x_{f-1}` the denoiser sees in
    training (normalized units, or for a ``delta`` model units of each feature's change; amdm
    only; :func:`~minimdm.amdm.losses.frame_loss`); 0: none."""
    cond_noise_motion: float = 0.0
    """Spread of Gaussian noise added, on top of ``cond_noise``, to the condition's motion
    features only: the root's d_x, d_y, d_r and the joint displacements j_v, in normalized
    frame units (a feature's spread over the training frames, for every model), so that the
    network cannot copy the previous frame's pace as it is and has to read it from the pose as
    well (chapter 3's fifth round: it trades a pace that grows for futures that halt; amdm
    only; :func:`~minimdm.amdm.losses.frame_loss`); 0: none."""
    cond_noise_draw: str = "fixed"
    """How each training condition's noise is sized: 'fixed' (every condition gets the spreads
    ``cond_noise`` and ``cond_noise_motion``), or 'uniform' (each condition's spreads are
    those times a factor drawn uniformly in [0, 1], so that the model meets departures of every
    size up to the spread: small ones to keep, large ones to undo)."""
    cond_noise_root: float = 1.0
    """A factor on the condition noise of the root's d_x, d_y, d_r, the pace (amdm only); 0
    shows the network the recorded pace, the pose still noised. Chapter 3's tenth round tried
    it on the guess that undoing a noised pace pulls every pace towards the commonest one: it
    kept less of each content's pace, not more."""
    cond_level: float | None = None
    """None: the network is not told how noisy its condition is. A level s in [0, 1] (needs
    ``cond_noise_draw: uniform``): the network also reads each training condition's drawn
    factor, and at run time s (:attr:`~minimdm.amdm.models.DenoiserConfig.cond_level`), so
    that it learns to undo large departures without assuming every condition is that far off.
    Chapter 3's thirteenth round tried it against the pull of the condition noise towards the
    commonest gait: a change model told any level from 0 to 1 kept its gait no better (amdm
    only)."""
    cond_noise_history: str = "each"
    """With a ``history`` of H > 1 frames: each frame of the condition gets its own draw of the
    condition noise ('each'), or all H the same draw ('shared': the past offset as a whole, the
    changes between its frames clean)."""
    delta_from: str = "seen"
    """From which previous frame a ``delta`` model's change is measured in training, with
    condition noise: 'seen' (the noised condition the network sees, so that the change also
    undoes the noise), or 'recorded' (the frame before the noise: the network learns the
    recorded change alone; :func:`~minimdm.amdm.losses.frame_loss`)."""
    clip_x0: float | str | None = "data"
    """Clamp x0 estimates when fed back and when sampling: 'data' (the per-feature range of the
    normalized training frames), a float c ([-c, c]), or None."""
    # ---- EMA, evaluation, checkpoints
    ema_decay: float = 0.999
    """Decay of the exponential moving average of the weights (0: no EMA)."""
    eval_interval: int = 500
    """Run the evaluation every this many steps (0: only at the end)."""
    eval_windows: int = 256
    """Held-in windows of the teacher-forced evaluation loss."""
    ckpt_interval: int = 500
    """Write a resumable checkpoint every this many steps (0: only at the end)."""
    log_interval: int = 50
    """Append the running training loss to log.jsonl every this many steps."""
    locomotion_share: float | None = None
    """Chance that a training window comes from a locomotion take (walk, walk-back, walk-left,
    walk-right, run, dash), split among those contents as ``locomotion_split`` says; the other
    takes share the rest by length. None: every window equally likely, so a take counts by its
    length (in bandai-namco-1's training takes: 55% locomotion, of which run and dash are 13%)."""
    locomotion_split: str = "equal"
    """How ``locomotion_share`` is split among the locomotion contents: 'equal' (each content
    the same; in bandai-namco-1 that shows a dash window 4x as often as the takes do) or
    'frames' (by length, as the takes have them, so only locomotion against the rest moves)."""
    storage: str = "float32"
    """Precision of the sampling weights in ``model.safetensors``: 'float32', or 'float16' /
    'bfloat16' (half the bytes; loading restores float32). The training state that resumes a
    run always keeps full precision."""
    seed: int = 0
    """Seeds the initial weights and every random draw of training."""
    # ---- data
    fps: float = 30.0
    """Frame rate the clips are resampled to (A-MDM: 30 Hz)."""
    corpus: str = "deepmimic"
    """The motion to learn: 'deepmimic' (20 clips of pybullet_data), a corpus name
    ('bandai-namco-1', or one fetched with `minimdm data download`), or a folder of BVH files."""
    split: str | None = None
    """'train' or 'test' takes of the corpus's fixed split, or None (all; a folder has no split)."""
    clips: list[str] | None = None
    """Names of the clips or takes to train on (None: all of them)."""
    extra_corpus: str | None = None
    """A second corpus (or folder of BVH files) of the same skeleton whose takes are all added to
    the training takes (its own split is not used: the held-out takes stay ``corpus``'s), e.g.
    'bandai-namco-2' (`minimdm data download bandai-namco-2`) for more walks and runs. The
    normalizer is fitted on both. None: ``corpus`` alone."""
    extra_contents: list[str] | None = None
    """Only the ``extra_corpus`` takes of these contents (their ``content`` label), e.g.
    ``[walk, run]``; None: all of its takes."""
    loop_frames: int | None = 150
    """Unroll looping clips to this many frames so windows cross the loop seam (None: 1 cycle;
    DeepMimic only: corpus takes do not loop)."""
    mirror: bool = False
    """Also train on every clip reflected left/right (:mod:`minimdm.motion.mirror`): twice the
    data, as many right turns as left ones. The held-out takes stay as recorded."""
    feature_scale: float = 1.0
    """Standardise every feature to this spread instead of 1 (the normalizer's std divided by
    it). The diffusion's noise levels stay as the schedule makes them, so a scale above 1 puts
    the least noisy level below the few hundredths by which a next frame varies: at T = 20 the
    cosine schedule's lowest noise is 0.09 of a feature's spread."""
    device: str = "cpu"
    """Where to train: 'cpu' or 'cuda'."""
    config_file: str | None = None
    """The YAML file this config came from (set by load_config; recorded in checkpoints)."""

    def __post_init__(self) -> None:
        if self.model_kind not in MODEL_KINDS:
            raise ValueError(f"model_kind must be one of {MODEL_KINDS}, got {self.model_kind!r}")
        counts = ("width", "depth", "T", "batch_size", "total_steps", "rollout", "log_interval")
        counts += ("history",)
        for name in counts + ("eval_windows",):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.depth < 2:
            raise ValueError(f"depth must be >= 2, got {self.depth}")
        if self.teacher_steps < 0 or self.ramp_steps < 0:
            raise ValueError(
                f"teacher_steps and ramp_steps must be >= 0, got {self.teacher_steps}, "
                f"{self.ramp_steps}"
            )
        if not (self.teacher_weight >= 0 and math.isfinite(self.teacher_weight)):
            raise ValueError(
                f"teacher_weight must be a finite float >= 0, got {self.teacher_weight}"
            )
        if self.norm not in ("l1", "l2"):
            raise ValueError(f"norm must be 'l1' or 'l2', got {self.norm!r}")
        if not (self.skip_sigma >= 0 and math.isfinite(self.skip_sigma)):
            raise ValueError(f"skip_sigma must be a finite float >= 0, got {self.skip_sigma}")
        if self.skip_features not in SKIP_FEATURES:
            raise ValueError(
                f"skip_features must be one of {SKIP_FEATURES}, got {self.skip_features!r}"
            )
        if not (self.feature_scale > 0 and math.isfinite(self.feature_scale)):
            raise ValueError(f"feature_scale must be a finite float > 0, got {self.feature_scale}")
        for name in ("skip_sigma_root", "skip_sigma_yaw"):
            value = getattr(self, name)
            if value is None:
                continue
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be a finite float >= 0 or null, got {value}")
            if self.predicts != "x0":
                raise ValueError(f"{name} needs predicts: x0, got {self.predicts!r}")
        if self.skip_sigma > 0 and self.predicts != "x0":
            raise ValueError(f"skip_sigma needs predicts: x0, got {self.predicts!r}")
        if self.snr_gamma is not None and not (
            self.snr_gamma > 0 and math.isfinite(self.snr_gamma)
        ):
            raise ValueError(f"snr_gamma must be a finite float > 0 or null, got {self.snr_gamma}")
        if not (self.snr_floor >= 0 and math.isfinite(self.snr_floor)):
            raise ValueError(f"snr_floor must be a finite float >= 0, got {self.snr_floor}")
        if self.locomotion_share is not None and not 0 < self.locomotion_share <= 1:
            raise ValueError(
                f"locomotion_share must lie in (0, 1] or be null, got {self.locomotion_share}"
            )
        if self.locomotion_split not in ("equal", "frames"):
            raise ValueError(
                f"locomotion_split must be 'equal' or 'frames', got {self.locomotion_split!r}"
            )
        if self.extra_contents is not None and self.extra_corpus is None:
            raise ValueError("extra_contents names contents of extra_corpus, which is null")
        if self.extra_corpus is not None and self.extra_corpus == self.corpus:
            raise ValueError(f"extra_corpus is the corpus itself ({self.corpus!r})")
        if self.storage not in ("float32", "float16", "bfloat16"):
            raise ValueError(
                f"storage must be 'float32', 'float16' or 'bfloat16', got {self.storage!r}"
            )
        if self.student_steps < 0:
            raise ValueError(f"student_steps must be >= 0, got {self.student_steps}")
        for name in ("geo_consistency", "geo_contact", "geo_bones"):
            w = getattr(self, name)
            if not (w >= 0 and math.isfinite(w)):
                raise ValueError(f"{name} must be a finite float >= 0, got {w}")
        for name in ("cond_noise", "cond_noise_motion"):
            spread = getattr(self, name)
            if not (spread >= 0 and math.isfinite(spread)):
                raise ValueError(f"{name} must be a finite float >= 0, got {spread}")
            if spread > 0 and self.model_kind != "amdm":
                raise ValueError(f"{name} needs model_kind: amdm, got {self.model_kind!r}")
        if not (0 <= self.cond_noise_root <= 1):
            raise ValueError(f"cond_noise_root must be in [0, 1], got {self.cond_noise_root}")
        if self.cond_noise_history not in ("each", "shared"):
            raise ValueError(
                f"cond_noise_history must be 'each' or 'shared', got {self.cond_noise_history!r}"
            )
        if self.delta_from not in ("seen", "recorded"):
            raise ValueError(f"delta_from must be 'seen' or 'recorded', got {self.delta_from!r}")
        if self.cond_level is not None:
            if not 0 <= self.cond_level <= 1:
                raise ValueError(f"cond_level must be in [0, 1] or null, got {self.cond_level}")
            if self.cond_noise_draw != "uniform" or self.model_kind != "amdm":
                raise ValueError(
                    "cond_level needs model_kind 'amdm' and cond_noise_draw 'uniform' (the levels "
                    f"it is told), got {self.model_kind!r} and {self.cond_noise_draw!r}"
                )
        if self.cond_noise_draw not in ("fixed", "uniform"):
            raise ValueError(
                f"cond_noise_draw must be 'fixed' or 'uniform', got {self.cond_noise_draw!r}"
            )
        if self.delta_features not in DELTA_FEATURES:
            raise ValueError(
                f"delta_features must be one of {DELTA_FEATURES}, got {self.delta_features!r}"
            )
        if self.delta and self.model_kind != "amdm":
            raise ValueError(f"delta needs model_kind: amdm, got {self.model_kind!r}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must lie in [0, 1), got {self.ema_decay}")


def load_config(path: str | os.PathLike) -> TrainConfig:
    """Read a YAML or TOML training config into a :class:`TrainConfig`.

    Unknown keys are an error and values take the field types (:func:`minimdm.config.load_config`).
    """
    return configs.load_config(path, TrainConfig)


def student_probability(config: TrainConfig, step: int) -> float:
    """Probability of feeding the model's own prediction at ``step`` (0-based).

    0 while ``step < teacher_steps``; then ``(step - teacher_steps) / ramp_steps`` up to 1.
    """
    if step < config.teacher_steps:
        return 0.0
    if config.ramp_steps == 0:
        return 1.0
    return min(1.0, (step - config.teacher_steps + 1) / config.ramp_steps)


def learning_rate(config: TrainConfig, step: int) -> float:
    """Cosine decay from ``lr`` to ``lr_min`` over ``total_steps`` (``minimdm.nn.cosine_lr``)."""
    return cosine_lr(step, config.total_steps, config.lr, config.lr_min)


def build_network(
    config: TrainConfig, x_dim: int, delta_scale: list[float] | None = None
) -> nn.Module:
    """The network of ``config.model_kind`` for frames of dimension ``x_dim``; a delta model
    (``config.delta``) needs the ``delta_scale`` of its data (:func:`delta_scale`)."""
    if config.model_kind == "amdm":
        from minimdm.diffusion import NoiseSchedule

        ac = NoiseSchedule(config.schedule, config.T).alphas_cumprod

        def weights(sigma: float | None) -> list[float] | None:  # c_skip(t) of a spread, or None
            return None if sigma is None else skip_weights(ac, sigma)

        skip = weights(config.skip_sigma) if config.skip_sigma > 0 else None
        mask = None
        if skip is not None and config.skip_features == "root":
            mask = root_mask(x_dim)
        dc = DenoiserConfig(
            x_dim,
            config.history * x_dim,
            config.width,
            config.depth,
            config.time_dim,
            config.predicts,
            skip,
            mask,
            weights(config.skip_sigma_root),
            weights(config.skip_sigma_yaw),
            _checked_delta_scale(config, x_dim, delta_scale),
            _delta_mask(config, x_dim),
            history=config.history,
            cond_level=config.cond_level,
        )
        return MLPDenoiser(dc)
    if config.model_kind == "mse":
        return MLPRegressor(x_dim, config.history * x_dim, config.width, config.depth)
    cond_dim = config.history * x_dim
    return MVAE(MVAEConfig(x_dim, cond_dim, config.latent_dim, config.width, config.depth))


def delta_scale(windows: Tensor, floor: float = 1e-3) -> list[float]:
    """Each feature's spread (D,) of the change between consecutive frames of ``windows``
    (W, N + 1, D), at least ``floor``: the scale :math:`k` of a delta model."""
    change = (windows[:, 1] - windows[:, 0]).double()  # (W, D)
    return change.std(0).clamp_min(floor).float().tolist()


def _checked_delta_scale(
    config: TrainConfig, x_dim: int, scale: list[float] | None
) -> list[float] | None:
    if not config.delta:
        return None
    if scale is None or len(scale) != x_dim:
        raise ValueError(f"a delta model needs delta_scale: {x_dim} values, got {scale!r}")
    return list(scale)


def _delta_mask(config: TrainConfig, x_dim: int) -> list[float] | None:
    """A delta model's mask (:attr:`DenoiserConfig.delta_mask`) for ``delta_features``: None
    (every feature) for 'all' and for models that are not delta models."""
    if not config.delta or config.delta_features == "all":
        return None
    if config.delta_features == "root":
        return root_mask(x_dim)
    n_joints = (x_dim - 3) // 12  # FeatureLayout: 3 + 12 J, the positions right after the root
    if config.delta_features == "rotations":  # j_o, the last 6 J
        return [0.0] * (3 + 6 * n_joints) + [1.0] * (6 * n_joints)
    root = 0.0 if config.delta_features == "joint_motion" else 1.0
    return [root] * 3 + [0.0] * (3 * n_joints) + [1.0] * (x_dim - 3 - 3 * n_joints)


def motion_mask(x_dim: int) -> list[float]:
    """1 for a frame's motion features, the root's d_x, d_y, d_r and the joint displacements
    j_v (FeatureLayout: 3 + 12 J, j_v after the positions j_p), 0 for the pose j_p, j_o."""
    n_joints = (x_dim - 3) // 12
    return [1.0] * 3 + [0.0] * (3 * n_joints) + [1.0] * (3 * n_joints) + [0.0] * (6 * n_joints)


def root_mask(x_dim: int) -> list[float]:
    """1 for the root's d_x, d_y, d_r (FeatureLayout's first three features), 0 elsewhere."""
    return [1.0] * 3 + [0.0] * (x_dim - 3)
