"""Training the motion AAMDM (Qiao et al. 2024, §4 and Algorithm 1), and its command line.

:func:`train_aamdm_motion` trains, in order, the autoencoder of the embedded space (eqs. 1-4), the
polisher (Algorithm 1 lines 7-18, eqs. 7-9) and the DD-GAN (lines 19-25, eqs. 11-12) on the
clips its config names (the Bandai-Namco training takes for the book's model), then writes one
checkpoint. ``python -m minimdm.aamdm train`` runs it (:func:`minimdm.cli.aamdm_main`);
reproduce the book's model with

    python -m minimdm.aamdm train configs/aamdm.yaml --ship   # -> checkpoints/aamdm/

(without ``--ship`` it writes to ``runs/aamdm/``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from minimdm import config as configs
from minimdm.aamdm.model import AAMDMConfig, DDGANDiscriminator, DiscriminatorConfig
from minimdm.aamdm.motion import (
    X_DIM,
    AAMDMMotion,
    MotionModelConfig,
    autoencoder_loss,
    clip_trajectory_features,
)
from minimdm.aamdm.train import GANConfig, PolishConfig, train_ddgan, train_polisher
from minimdm.checkpoint import save_checkpoint
from minimdm.diffusion import NoiseSchedule, data_range
from minimdm.files import RunLock
from minimdm.nn import cosine_lr, optimizer_step, set_lr
from minimdm.validate import InputError, check_int, check_number, check_output_dir

__all__ = [
    "AAMDMTrainConfig",
    "load_train_config",
    "load_motion_data",
    "train_aamdm_motion",
    "checkpoint_training_xz",
]


@dataclass
class AAMDMTrainConfig:
    """A motion AAMDM run; ``configs/aamdm_*.yaml`` load into it."""

    fps: float = 30.0
    """Frame rate of the clips."""
    corpus: str = "deepmimic"
    """The motion: 'deepmimic', a corpus name or a BVH folder, as ``TrainConfig.corpus``
    (:func:`minimdm.motion.corpora.load_motion`)."""
    split: str | None = None
    """'train' or 'test' takes of the corpus's fixed split, or None (all)."""
    clips: list[str] | None = None
    """Clip or take names (None: all of them)."""
    loop_frames: int | None = 150
    """Unroll looping clips to this many frames (DeepMimic only)."""
    mirror: bool = False
    """Also train on every clip reflected left/right (:mod:`minimdm.motion.mirror`), as the base
    A-MDM does: twice the frames, as many right turns as left ones."""
    locomotion_share: float | None = None
    """The share of training draws (frame pairs and windows) from the locomotion takes, split
    equally among their contents, as the base A-MDM's ``locomotion_share``
    (:func:`minimdm.amdm.train.window_weights`); None: every frame equally often."""
    horizons: list[int] = field(default_factory=lambda: [10, 20, 30])
    """Frames ahead of the future-trajectory features x."""
    z_dim: int = 24
    """Size of the learned latent z."""
    ae_width: int = 256
    """Hidden units of the autoencoder."""
    ae_depth: int = 3
    """Layers of the encoder and of the decoder."""
    ae_steps: int = 2000
    """Autoencoder optimizer steps."""
    ae_batch: int = 256
    """Pairs of consecutive frames per autoencoder step."""
    ae_lr: float = 1e-3
    """Autoencoder learning rate (cosine-decayed)."""
    w_val: float = 1.0
    """Weight of L_val (eq. 1)."""
    w_vel: float = 1.0
    """Weight of L_vel (eq. 2)."""
    w_reg: float = 0.01
    """Weight of L_reg (eq. 3)."""
    T_gan: int = 3
    """DD-GAN steps."""
    T_adm: int = 2
    """Polishing steps."""
    latent_dim: int = 8
    """Size of the GAN latent r."""
    width: int = 256
    """Hidden units of the generator and the polisher."""
    depth: int = 4
    """Layers of the generator and the polisher."""
    disc_width: int = 256
    """Hidden units of the discriminator."""
    fourier: int = 0
    """Random Fourier features in the generator and the discriminator."""
    window: int = 4
    """h: frames per training window of the polisher's rollout (paper: 10)."""
    polish_steps: int = 2000
    """Polisher optimizer steps."""
    polish_batch: int = 64
    """Windows per polisher step."""
    polish_lr: float = 1e-3
    """Polisher learning rate."""
    polish_w_vel: float = 1.0
    """Weight of the velocity loss of eq. 8 (on x)."""
    gan_steps: int = 8000
    """DD-GAN optimizer steps."""
    gan_batch: int = 64
    """Windows per DD-GAN step."""
    lr_g: float = 2e-4
    """Generator learning rate."""
    lr_d: float = 4e-4
    """Discriminator learning rate."""
    r1_gamma: float = 0.3
    """R1 penalty weight."""
    clip_x0: float | str | None = "data"
    """Clamp x0 estimates while sampling: 'data' (the per-feature range of the standardised xz
    training data), a float c ([-c, c], standardised units) or None."""
    seed: int = 0
    """Seeds everything."""
    config_file: str | None = None
    """The YAML file this config came from (set by load_train_config)."""

    def __post_init__(self) -> None:
        autoencoder = ("z_dim", "ae_width", "ae_depth", "ae_steps", "ae_batch")
        transition = ("T_gan", "latent_dim", "width", "depth", "disc_width", "window")
        loops = ("polish_steps", "polish_batch", "gan_steps", "gan_batch")
        for name in autoencoder + transition + loops:
            check_int(name, getattr(self, name), low=1)
        check_int("T_adm", self.T_adm, low=0)
        check_int("fourier", self.fourier, low=0)
        if not self.horizons:
            raise InputError("horizons must list at least one number of frames ahead, got []")
        for i, h in enumerate(self.horizons):
            check_int(f"horizons[{i}]", h, low=1)
        check_number("fps", self.fps, low=1.0, high=1000.0)
        for name in ("ae_lr", "polish_lr", "lr_g", "lr_d"):
            check_number(name, getattr(self, name), low=0.0, low_open=True)
        for name in ("w_val", "w_vel", "w_reg", "polish_w_vel", "r1_gamma"):
            check_number(name, getattr(self, name), low=0.0)
        if self.locomotion_share is not None:
            check_number("locomotion_share", self.locomotion_share, low=0.0, high=1.0)


def load_train_config(path: str | Path) -> AAMDMTrainConfig:
    """Read a YAML or TOML file into an :class:`AAMDMTrainConfig`; unknown keys are an error."""
    return configs.load_config(path, AAMDMTrainConfig)


def load_motion_data(config: AAMDMTrainConfig) -> dict[str, Any]:
    """Clips, per-clip features ``y`` (F_i - 1, D) and ``x`` (F_i - 1, 12), and the normalizer.

    ``clips`` are the takes as loaded; with ``config.mirror`` the features also hold their mirror
    images, after them."""
    from minimdm.motion import features
    from minimdm.motion.corpora import load_motion
    from minimdm.motion.mirror import mirror_clips

    clips = load_motion(
        config.corpus, config.split, config.fps, config.clips, config.loop_frames
    )  # the clips A-MDM's trainer would load for the same fields
    frames_of = list(clips) + (mirror_clips(list(clips)) if config.mirror else [])
    ys = [features.encode(c) for c in frames_of]
    xs = [clip_trajectory_features(c, tuple(config.horizons)) for c in frames_of]
    skeleton = clips[0].skeleton  # actors' bone lengths may differ; the topology may not
    return {
        "clips": clips,
        "contents": [c.labels.get("content") for c in frames_of],
        "y": ys,
        "x": xs,
        "normalizer": features.Normalizer.fit(ys),
        "skeleton": skeleton,
        "layout": features.FeatureLayout.for_skeleton(skeleton, config.fps),
    }


def _weights(c: AAMDMTrainConfig, d: dict[str, Any], arrays: list[Tensor], n: int) -> Tensor | None:
    """Draw weights of the (n + 1)-frame windows of ``arrays`` for ``c.locomotion_share``."""
    if c.locomotion_share is None:
        return None
    from minimdm.amdm.train import window_weights

    return window_weights([len(a) for a in arrays], n, d["contents"], c.locomotion_share)


def _pairs(arrays: list[Tensor]) -> Tensor:
    return torch.cat([torch.stack([a[:-1], a[1:]], dim=1) for a in arrays])  # (N, 2, D)


def train_aamdm_motion(
    config: AAMDMTrainConfig,
    out_dir: str | Path | None = None,
    progress: bool = True,
    command: str | None = None,
) -> tuple[AAMDMMotion, dict]:
    """Train the autoencoder, then the polisher, then the DD-GAN (AAMDM §4 and Algorithm 1).

    Writes ``out_dir/model.safetensors`` and ``model.json`` (plus the GAN's resumable
    ``model.train.safetensors``) when ``out_dir`` is given, holding its run lock
    (:class:`minimdm.files.RunLock`) meanwhile. ``command`` is recorded in the checkpoint
    (default ``python -m minimdm.aamdm train CONFIG``). Returns the model and a report of the
    training times and final losses.
    """
    if out_dir is None:
        return _train(config, None, progress, command)
    out_dir = check_output_dir("out_dir", out_dir)
    with RunLock(out_dir, command):  # one run per folder
        return _train(config, out_dir, progress, command)


def _train(
    config: AAMDMTrainConfig, out_dir: Path | None, progress: bool, command: str | None
) -> tuple[AAMDMMotion, dict]:
    from minimdm.amdm.losses import make_windows

    c = config
    log = print if progress else (lambda *a, **k: None)
    t_all = time.perf_counter()
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)  # a folder: model.* inside it
    d = load_motion_data(c)
    model, ys, xs = _new_model(c, d)
    report: dict[str, Any] = {"frames": int(sum(len(y) for y in ys))}

    # 1. the autoencoder, on pairs of consecutive frames (eqs. 1-4)
    t0 = time.perf_counter()
    info = _train_autoencoder(model, ys, xs, d, c, log, _weights(c, d, ys, 1))
    report["autoencoder_s"] = time.perf_counter() - t0
    report["autoencoder"] = _round(info)

    # 2. the embedded vectors xz of every frame, standardised
    xz = _embed(model, ys, xs, c)
    windows = make_windows(xz, c.window)  # (W, h + 1, X + Z)
    weights = _weights(c, d, xz, c.window)
    report["windows"] = int(windows.shape[0])

    # 3. the polisher (Algorithm 1 lines 7-18), velocities on x (eq. 8)
    tr = model.transition
    sch = tr.schedule("cpu")
    pcfg = PolishConfig(c.polish_steps, c.polish_batch, c.polish_lr, c.polish_w_vel, seed=c.seed)
    t0 = time.perf_counter()
    hist = train_polisher(
        tr.polisher, sch, windows, c.T_adm, pcfg, vel_dims=slice(0, X_DIM), weights=weights
    )
    report["polisher_s"] = time.perf_counter() - t0
    report["polisher"] = _round(hist[-1])
    log(f"polisher: {json.dumps(report['polisher'])} in {report['polisher_s']:.0f} s", flush=True)

    # 4. the DD-GAN, conditioned on the polisher's rollouts (lines 19-25)
    meta = _metadata(c, d, command, windows)
    t0 = time.perf_counter()
    gan_hist = _train_gan(model, sch, windows, c, out_dir, meta, log, weights)
    report["gan_s"] = time.perf_counter() - t0
    report["gan"] = _round(gan_hist[-1], _GAN_KEYS)
    report["total_s"] = time.perf_counter() - t_all
    model.eval()
    if out_dir is not None:
        meta.update(step=c.gan_steps, report=report)
        save_checkpoint(out_dir, model, meta)
    return model, report


_GAN_KEYS = ("loss_d", "loss_g", "d_real", "d_fake")
"""The DD-GAN record's entries that the log and the report keep."""


def _new_model(
    c: AAMDMTrainConfig, d: dict[str, Any]
) -> tuple[AAMDMMotion, list[Tensor], list[Tensor]]:
    """The untrained model, seeded, holding the statistics of ``y`` and ``x`` of the data ``d``;
    and the standardised ``y`` and ``x`` of every clip."""
    norm = d["normalizer"]
    x_all = torch.cat(d["x"])
    x_mean, x_std = x_all.mean(0), x_all.std(0).clamp_min(1e-3)
    ys = [norm.normalize(y) for y in d["y"]]
    xs = [(x - x_mean) / x_std for x in d["x"]]
    xz_dim = X_DIM + c.z_dim
    clip_x0 = None if c.clip_x0 == "data" else c.clip_x0  # 'data' is set once xz is known
    tcfg = AAMDMConfig(
        xz_dim,
        xz_dim,
        c.T_gan,
        c.T_adm,
        latent_dim=c.latent_dim,
        width=c.width,
        depth=c.depth,
        fourier=c.fourier,
        clip_x0=clip_x0,
    )
    mcfg = MotionModelConfig(
        norm.dim, X_DIM, c.z_dim, c.ae_width, c.ae_depth, list(c.horizons), asdict(tcfg)
    )
    torch.manual_seed(c.seed)
    model = AAMDMMotion(mcfg)
    model.y_mean.copy_(norm.mean)
    model.y_std.copy_(norm.std)
    model.x_mean.copy_(x_mean)
    model.x_std.copy_(x_std)
    return model, ys, xs


def _train_autoencoder(
    model: AAMDMMotion,
    ys: list[Tensor],
    xs: list[Tensor],
    d: dict[str, Any],
    c: AAMDMTrainConfig,
    log: Callable[..., None],
    weights: Tensor | None = None,
) -> dict[str, float]:
    """Fit the autoencoder on pairs of consecutive frames (eqs. 1-4), drawn by ``weights`` when
    given; its last step's losses."""
    y_pairs, x_pairs = _pairs(ys), _pairs(xs)
    ae = model.autoencoder
    opt = torch.optim.Adam(ae.parameters(), lr=c.ae_lr)
    g = torch.Generator().manual_seed(c.seed)
    denormalize, skeleton = d["normalizer"].denormalize, d["skeleton"]
    for step in range(c.ae_steps):
        set_lr(opt, cosine_lr(step, c.ae_steps, c.ae_lr, c.ae_lr / 20))
        if weights is None:
            idx = torch.randint(0, len(y_pairs), (c.ae_batch,), generator=g)
        else:
            idx = torch.multinomial(weights, c.ae_batch, replacement=True, generator=g)
        loss, info = autoencoder_loss(
            ae, y_pairs[idx], x_pairs[idx], denormalize, skeleton, c.w_val, c.w_vel, c.w_reg
        )
        optimizer_step(opt, loss, list(ae.parameters()), grad_clip=1.0)
        if (step + 1) % 500 == 0:
            log(f"autoencoder {step + 1}/{c.ae_steps}: {json.dumps(_round(info))}", flush=True)
    ae.eval()
    return info


@torch.no_grad()
def _embed(
    model: AAMDMMotion, ys: list[Tensor], xs: list[Tensor], c: AAMDMTrainConfig
) -> list[Tensor]:
    """The standardised xz of every clip; stores their statistics in ``model``, and with
    ``clip_x0 = 'data'`` their range as the sampler's clamp."""
    xz_raw = [
        torch.cat([x, model.autoencoder.encode(y)], dim=-1) for x, y in zip(xs, ys, strict=True)
    ]
    cat = torch.cat(xz_raw)
    model.xz_mean.copy_(cat.mean(0))
    model.xz_std.copy_(cat.std(0).clamp_min(1e-3))
    xz = [(a - model.xz_mean) / model.xz_std for a in xz_raw]
    if c.clip_x0 == "data":  # the sampler's clamp: the range of the standardised training xz
        lo, hi = data_range(xz)
        model.transition.config.clip_x0 = [lo.tolist(), hi.tolist()]
        model.config.transition["clip_x0"] = model.transition.config.clip_x0
    return xz


def _metadata(
    c: AAMDMTrainConfig, d: dict[str, Any], command: str | None, windows: Tensor
) -> dict[str, Any]:
    """The checkpoint's metadata: the config, the command, the layout and the data."""
    return {
        "config": asdict(c),
        "config_file": c.config_file,
        "command": command or f"python -m minimdm.aamdm train {c.config_file}",
        "feature_layout": d["layout"],
        "skeleton": d["skeleton"],
        "normalizer": d["normalizer"],
        "data": {
            "corpus": c.corpus,
            "split": c.split,
            "clips": d["clips"].names,
            "fps": c.fps,
            "windows": int(windows.shape[0]),
        },
    }


def _train_gan(
    model: AAMDMMotion,
    schedule: NoiseSchedule,
    windows: Tensor,
    c: AAMDMTrainConfig,
    out_dir: Path | None,
    meta: dict[str, Any],
    log: Callable[..., None],
    weights: Tensor | None = None,
) -> list[dict]:
    """The DD-GAN on the windows (drawn by ``weights`` when given), conditioned on the
    polisher's rollouts (lines 19-25), checkpointed into ``out_dir`` every 1000 steps; its
    history."""
    xz_dim = X_DIM + c.z_dim
    disc = DDGANDiscriminator(
        DiscriminatorConfig(xz_dim, xz_dim, c.disc_width, 3, 64, fourier=c.fourier)
    )
    gcfg = GANConfig(
        c.gan_steps,
        c.gan_batch,
        c.lr_g,
        c.lr_d,
        r1_gamma=c.r1_gamma,
        seed=c.seed,
        ckpt_interval=1000,
    )

    def tick(step: int, rec: dict) -> None:
        if step % 500 == 0:
            log(f"dd-gan {step}/{c.gan_steps}: {json.dumps(_round(rec, _GAN_KEYS))}", flush=True)

    tr = model.transition
    return train_ddgan(
        tr.generator,
        disc,
        schedule,
        windows,
        c.T_gan,
        gcfg,
        polisher=tr.polisher,
        checkpoint=out_dir,
        bundle=model,
        metadata=meta,
        resume=False,
        callback=tick,
        weights=weights,
    )


@torch.no_grad()
def checkpoint_training_xz(ckpt: Any) -> Tensor:
    """The standardised xz (N, X + Z) a motion AAMDM checkpoint was trained on, rebuilt.

    The clips are loaded as its config loaded them and embedded with the checkpoint's own
    autoencoder and statistics, clip by clip, as in training: the frames its x0 clamp must cover.
    """
    cfg = dict(ckpt.config)
    cfg["clips"] = (ckpt.metadata.get("data") or {}).get("clips") or cfg.get("clips")
    d = load_motion_data(AAMDMTrainConfig(**cfg))
    model = ckpt.model
    return torch.cat([model.encode(y, x) for y, x in zip(d["y"], d["x"], strict=True)])


def _round(d: dict, keys: tuple[str, ...] | None = None) -> dict:
    return {k: round(float(v), 5) for k, v in d.items() if keys is None or k in keys}
