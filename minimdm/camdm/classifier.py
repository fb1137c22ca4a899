"""A style classifier over 60-frame clips, so that "style accuracy" (CAMDM §4.1, metric 7) and a
Fréchet distance on its features (standing in for the paper's FID, metric 1) mean something.

The classifier sees what a viewer sees: the joint positions and rotations of the clip, by
forward kinematics of *one* reference skeleton (the bone lengths of the corpus's actors differ
by style, and a generated character has the model's), encoded per frame in the character's own
heading frame (the A-MDM features, :func:`minimdm.motion.features.encode_motion`), so that
neither where nor which way the character walks tells the style. A small 1D convolution over
time pools them into a feature vector, and a linear layer gives the style.

``minimdm camdm classifier configs/camdm_classifier.yaml`` trains it on the training takes and
records its accuracy on the held-out takes' clips in the checkpoint (``heldout_accuracy``).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from minimdm import config as configs
from minimdm.checkpoint import (
    Checkpoint,
    CheckpointMismatchError,
    load_checkpoint,
    register_model_kind,
    save_checkpoint,
)
from minimdm.files import RunLock, atomic_write
from minimdm.motion.features import Normalizer, encode_motion
from minimdm.motion.mirror import mirror_clips
from minimdm.motion.skeleton import Skeleton, forward_kinematics
from minimdm.nn import cosine_lr, optimizer_step, set_lr
from minimdm.utils import num_threads as threads
from minimdm.validate import InputError, check_int, check_number, check_output_dir

from .data import _split, world_frames

__all__ = [
    "ClassifierConfig",
    "StyleClassifier",
    "load_classifier_config",
    "motion_features",
    "train_classifier",
    "load_classifier",
    "predict_styles",
    "style_accuracy",
    "classifier_features",
    "frechet_distance",
]


@dataclass
class ClassifierConfig:
    """A style-classifier run; ``configs/camdm_classifier.yaml`` loads into it."""

    window: int = 60
    """Frames per clip (CAMDM: 60)."""
    width: int = 128
    """Channels of the convolutions."""
    feature_dim: int = 64
    """Size of the pooled feature vector (the Fréchet distance's space)."""
    dropout: float = 0.2
    """Dropout before the last layer."""
    steps: int = 3000
    """Optimizer steps."""
    batch_size: int = 64
    """Clips per step."""
    lr: float = 1e-3
    """Adam learning rate (cosine-decayed to a tenth)."""
    eval_stride: int = 10
    """Frames between the starts of the held-out clips."""
    seed: int = 0
    """Seeds everything."""
    fps: float = 30.0
    """Frame rate."""
    corpus: str = "bandai-namco-1"
    """The labelled corpus."""
    contents: list[str] | None = None
    """Contents of the takes (None: locomotion, as CAMDM's)."""
    mirror: bool = False
    """Also learn from every training take reflected left/right (:mod:`minimdm.motion.mirror`),
    so that a mirrored walk is judged by its style, not by its side; the held-out accuracy is
    still measured on the takes as recorded."""
    config_file: str | None = None
    """The file this config came from."""

    def __post_init__(self) -> None:
        for name in ("window", "width", "feature_dim", "steps", "batch_size", "eval_stride"):
            check_int(name, getattr(self, name), low=2 if name == "window" else 1)
        check_number("dropout", self.dropout, low=0.0, high=0.99)
        check_number("lr", self.lr, low=0.0, low_open=True)
        check_number("fps", self.fps, low=1.0, high=1000.0)


def load_classifier_config(path: str | os.PathLike) -> ClassifierConfig:
    """Read a YAML or TOML file into a :class:`ClassifierConfig`."""
    return configs.load_config(path, ClassifierConfig)


@dataclass
class ClassifierNetConfig:
    """The network's size."""

    in_dim: int
    n_styles: int
    width: int = 128
    feature_dim: int = 64
    dropout: float = 0.2


class StyleClassifier(nn.Module):
    """``forward(x) -> logits``: clips of per-frame features ``(B, W, C)`` -> ``(B, n_styles)``;
    :meth:`features` gives the pooled vector ``(B, feature_dim)``."""

    def __init__(self, config: ClassifierNetConfig) -> None:
        super().__init__()
        self.config = c = config
        w = c.width
        self.convs = nn.Sequential(  # (B, C, W) -> (B, width, ceil(W / 4))
            nn.Conv1d(c.in_dim, w, 5, padding=2),
            nn.GELU(),
            nn.Conv1d(w, w, 5, stride=2, padding=2),
            nn.GELU(),
            nn.Conv1d(w, w, 5, stride=2, padding=2),
            nn.GELU(),
        )
        self.project = nn.Linear(2 * w, c.feature_dim)
        self.head = nn.Sequential(
            nn.GELU(), nn.Dropout(c.dropout), nn.Linear(c.feature_dim, c.n_styles)
        )

    def features(self, x: Tensor) -> Tensor:
        h = self.convs(x.transpose(1, 2))  # (B, W', T')
        return self.project(torch.cat([h.mean(-1), h.amax(-1)], -1))  # (B, feature_dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.head(self.features(x))


register_model_kind(
    "style_classifier",
    StyleClassifier,
    lambda c: StyleClassifier(ClassifierNetConfig(**c)),
    lambda m: asdict(m.config),
)


def motion_features(frames: Tensor, skeleton: Skeleton) -> Tensor:
    """Per-frame classifier input ``(..., N - 1, 3 + 12 J)`` of world frames ``(..., N, D)``
    (:mod:`minimdm.camdm.data`): FK of ``skeleton``, then the A-MDM encoding."""
    root, rot = _split(frames.double())
    pos, grot = forward_kinematics(skeleton, root, rot)
    return encode_motion(pos, grot, skeleton.lateral_axis).float()


def _clips(feats: list[Tensor], window: int, stride: int) -> tuple[Tensor, Tensor]:
    """(take index, first row) of every ``window - 1``-row clip at ``stride``."""
    rows = window - 1
    idx = [(i, s) for i, f in enumerate(feats) for s in range(0, f.shape[0] - rows + 1, stride)]
    t = torch.tensor(idx, dtype=torch.long).reshape(-1, 2)
    return t[:, 0], t[:, 1]


def _gather(feats: list[Tensor], take: Tensor, start: Tensor, rows: int) -> Tensor:
    return torch.stack(
        [feats[int(i)][int(s) : int(s) + rows] for i, s in zip(take, start, strict=True)]
    )


def train_classifier(
    config: ClassifierConfig,
    out_dir: str | os.PathLike,
    *,
    progress: bool = True,
    num_threads: int | None = None,
    metadata: dict[str, Any] | None = None,
) -> Checkpoint:
    """Train the style classifier on the training takes; the checkpoint records its accuracy on
    every ``window``-frame clip of the held-out takes (``heldout_accuracy``)."""
    from .train import load_clips

    out_dir = Path(check_output_dir("out_dir", out_dir))
    with threads(num_threads), RunLock(out_dir, (metadata or {}).get("command")):  # one run
        train = load_clips(config.corpus, "train", config.fps, config.contents)
        train = train + mirror_clips(train) if config.mirror else train
        test = load_clips(config.corpus, "test", config.fps, config.contents)
        styles = sorted({c.labels["style"] for c in train})
        skeleton = train[0].skeleton
        f_train = [motion_features(world_frames(c), skeleton) for c in train]
        f_test = [
            motion_features(world_frames(c), skeleton) for c in test if c.labels["style"] in styles
        ]
        y_train = torch.tensor([styles.index(c.labels["style"]) for c in train])
        y_test = torch.tensor(
            [styles.index(c.labels["style"]) for c in test if c.labels["style"] in styles]
        )
        norm = Normalizer.fit(f_train)
        f_train = [norm.normalize(f) for f in f_train]
        f_test = [norm.normalize(f) for f in f_test]
        rows = config.window - 1
        tr_take, tr_start = _clips(f_train, config.window, 1)
        te_take, te_start = _clips(f_test, config.window, config.eval_stride)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            size = (config.width, config.feature_dim, config.dropout)
            net = StyleClassifier(ClassifierNetConfig(f_train[0].shape[-1], len(styles), *size))
        opt = torch.optim.Adam(net.parameters(), lr=config.lr)
        gen = torch.Generator().manual_seed(config.seed)
        log_path = out_dir / "log.jsonl"
        out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write(log_path, "")
        t0 = time.perf_counter()

        def accuracy() -> float:
            net.eval()
            with torch.no_grad():
                x = _gather(f_test, te_take, te_start, rows)
                acc = (net(x).argmax(-1) == y_test[te_take]).float().mean().item()
            net.train()
            return acc

        net.train()
        for step in tqdm(range(config.steps), disable=not progress, desc="style classifier"):
            set_lr(opt, cosine_lr(step, config.steps, config.lr, config.lr / 10))
            pick = torch.randint(len(tr_take), (config.batch_size,), generator=gen)
            x = _gather(f_train, tr_take[pick], tr_start[pick], rows)
            loss = nn.functional.cross_entropy(net(x), y_train[tr_take[pick]])
            optimizer_step(opt, loss, list(net.parameters()))
            if (step + 1) % 250 == 0 or step + 1 == config.steps:
                rec = {"step": step + 1, "loss": loss.item(), "heldout_accuracy": accuracy()}
                with open(log_path, "a") as f:
                    f.write(json.dumps(rec) + "\n")
        acc = accuracy()
        meta = {
            **(metadata or {}),
            "config": asdict(config),
            "config_file": config.config_file,
            "styles": styles,
            "skeleton": skeleton,
            "normalizer": norm,
            "step": config.steps,
            "heldout_accuracy": round(acc, 4),
            "heldout_clips": int(len(te_take)),
            "train_seconds": round(time.perf_counter() - t0, 1),
            "data": {"train": [c.name for c in train], "test": [c.name for c in test]},
        }
        save_checkpoint(out_dir, net.eval(), meta)
    return load_checkpoint(out_dir)


def load_classifier(
    path: str | os.PathLike, expected_styles: list[str] | tuple[str, ...] | None = None
) -> Checkpoint:
    """Load a style classifier; one trained on another style set than ``expected_styles`` (e.g.
    a CAMDM model's) is refused, naming both."""
    ckpt = load_checkpoint(path)
    if ckpt.kind != "style_classifier":
        raise CheckpointMismatchError(
            f"checkpoint {ckpt.paths.weights} holds a {ckpt.kind!r} model, not a style classifier"
        )
    styles = list(ckpt.metadata.get("styles", []))
    if expected_styles is not None and list(expected_styles) != styles:
        raise CheckpointMismatchError(
            f"classifier {ckpt.paths.weights} was trained on another style set: the classifier's "
            f"styles are {styles}, the expected styles are {list(expected_styles)}"
        )
    return ckpt


def _inputs(ckpt: Checkpoint, frames: Tensor) -> Tensor:
    """Normalized per-frame features of every ``window``-frame clip of world frames (B, N, D):
    (B, n_clips, window - 1, C), clips one after the other."""
    window = int(ckpt.config.get("window", 60))
    if frames.dim() != 3 or frames.shape[1] < window:
        raise InputError(
            f"frames must be world frames of shape (B, N >= {window}, D), got {tuple(frames.shape)}"
        )
    n = frames.shape[1] // window
    clips = frames[:, : n * window].reshape(frames.shape[0], n, window, -1)
    feats = motion_features(clips, Skeleton.from_dict(ckpt.skeleton))
    return Normalizer.from_dict(ckpt.normalizer).normalize(feats)


@torch.no_grad()
def predict_styles(ckpt: Checkpoint, frames: Tensor) -> Tensor:
    """The style index of every consecutive ``window``-frame clip: (B, n_clips)."""
    x = _inputs(ckpt, frames)
    return ckpt.model(x.flatten(0, 1)).argmax(-1).view(x.shape[:2])


def style_accuracy(ckpt: Checkpoint, frames: Tensor, styles: Tensor) -> float:
    """The share of the clips of ``frames (B, N, D)`` classified as their style ``(B,)``."""
    pred = predict_styles(ckpt, frames)
    return (pred == torch.as_tensor(styles).view(-1, 1)).float().mean().item()


@torch.no_grad()
def classifier_features(ckpt: Checkpoint, frames: Tensor) -> Tensor:
    """The classifier's features of every consecutive clip: (B n_clips, feature_dim)."""
    x = _inputs(ckpt, frames)
    return ckpt.model.features(x.flatten(0, 1))


def _sqrt_psd(a: Tensor) -> Tensor:
    vals, vecs = torch.linalg.eigh(a)
    return vecs @ torch.diag(vals.clamp_min(0).sqrt()) @ vecs.T


def frechet_distance(a: Tensor, b: Tensor) -> float:
    """The Fréchet distance of two sets of features ``(n, d)``, ``(m, d)`` under Gaussian fits
    (Heusel et al. 2017): :math:`\\|\\mu_a - \\mu_b\\|^2 + \\mathrm{tr}(\\Sigma_a + \\Sigma_b -
    2(\\Sigma_a^{1/2}\\Sigma_b\\Sigma_a^{1/2})^{1/2})`."""
    a, b = a.double(), b.double()
    if a.dim() != 2 or b.dim() != 2 or a.shape[1] != b.shape[1] or min(len(a), len(b)) < 2:
        raise InputError(
            f"features must have shapes (n >= 2, d) and (m >= 2, d), got {tuple(a.shape)} and "
            f"{tuple(b.shape)}"
        )
    mu = (a.mean(0) - b.mean(0)).pow(2).sum()
    sa, sb = torch.cov(a.T).reshape(a.shape[1], -1), torch.cov(b.T).reshape(b.shape[1], -1)
    ra = _sqrt_psd(sa)
    cross = _sqrt_psd(ra @ sb @ ra)
    return float(mu + torch.trace(sa + sb - 2 * cross))
