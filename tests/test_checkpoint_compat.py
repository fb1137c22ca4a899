"""Every shipped checkpoint loads strictly and computes what the networks computed before they
shared :class:`minimdm.nn.MLP`. The MVAE is not among them: its shipped weights were renamed once
to the names of its :class:`~minimdm.nn.MLP` decoder, and nothing keeps the old ones.

The reference below is the old forward code, written out as functions of the raw state dict
(``F.linear``, ``F.silu``, ``F.layer_norm``, exactly as the old modules called them). It reads
every tensor by its checkpoint name, so it also pins the state-dict keys: each test checks that
the reference read every key of the network and nothing else.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor

import minimdm
from minimdm.aamdm.model import AAMDM
from minimdm.aamdm.motion import AAMDMMotion
from minimdm.aamdm.nets import (
    DDGANDiscriminator,
    DDGANGenerator,
    DiscriminatorConfig,
    GeneratorConfig,
)
from minimdm.amdm.models import DenoiserConfig, MLPDenoiser, MLPRegressor, timestep_embedding
from minimdm.camdm.classifier import ClassifierNetConfig, StyleClassifier
from minimdm.camdm.model import CAMDM, CAMDMConfig, Conditions
from minimdm.checkpoint import load_checkpoint
from minimdm.rl.policy import PolicyNet

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINTS = ROOT / "checkpoints"
B = 5


class Recorder(dict):
    """A state dict that remembers which keys were read."""

    def __init__(self, sd: dict[str, Tensor]) -> None:
        super().__init__(sd)
        self.read: set[str] = set()

    def __getitem__(self, key: str) -> Tensor:
        self.read.add(key)
        return super().__getitem__(key)


# ---- the old forward code, on raw state dicts ------------------------------------------------


def _lin(sd, name: str, x: Tensor) -> Tensor:
    return F.linear(x, sd[f"{name}.weight"], sd[f"{name}.bias"])


def _ln(sd, name: str, x: Tensor) -> Tensor:
    return F.layer_norm(x, (x.shape[-1],), sd[f"{name}.weight"], sd[f"{name}.bias"], 1e-5)


def old_sequential(sd, p: str, x: Tensor) -> Tensor:
    """nn.Sequential(Linear, SiLU, LayerNorm, ..., Linear): keys p0, p2, p3, p5, ..."""
    i = 0
    while f"{p}{i + 3}.weight" in sd:
        x = _ln(sd, f"{p}{i + 2}", F.silu(_lin(sd, f"{p}{i}", x)))
        i += 3
    return _lin(sd, f"{p}{i}", x)


def old_time_mlp(sd, p: str, v: Tensor) -> Tensor:
    """nn.Sequential(Linear, SiLU, Linear)."""
    return _lin(sd, f"{p}2", F.silu(_lin(sd, f"{p}0", v)))


def old_body(sd, p: str, h: Tensor, e: Tensor, act=F.silu, norm: bool = True) -> Tensor:
    """input, hidden.i, norms.i, output, with ``e`` added to every hidden layer."""
    h = act(_lin(sd, f"{p}input", h) + e)
    h = _ln(sd, f"{p}norms.0", h) if norm else h
    i = 0
    while f"{p}hidden.{i}.weight" in sd:
        h = act(_lin(sd, f"{p}hidden.{i}", h) + e)
        h = _ln(sd, f"{p}norms.{i + 1}", h) if norm else h
        i += 1
    return _lin(sd, f"{p}output", h)


def old_denoiser(sd, p: str, cfg: dict, x_t, t, cond) -> Tensor:
    h = torch.cat([x_t, cond], -1) if cfg["cond_dim"] else x_t
    e = old_time_mlp(sd, f"{p}time_mlp.", timestep_embedding(t, cfg["time_dim"]))
    out = old_body(sd, p, h, e)
    if cfg.get("skip") or cfg.get("skip_root") or cfg.get("skip_yaw"):  # c_skip(t) x_t, per feature
        n = len(cfg.get("skip") or cfg.get("skip_root") or cfg["skip_yaw"])
        w = torch.zeros(n, cfg["x_dim"])
        if cfg.get("skip"):
            mask = torch.tensor(cfg.get("skip_mask") or [1.0] * cfg["x_dim"])
            w = torch.tensor(cfg["skip"])[:, None] * mask
        for key, cols in (("skip_root", slice(0, 3)), ("skip_yaw", slice(2, 3))):
            if cfg.get(key):
                w[:, cols] = torch.tensor(cfg[key])[:, None]
        out = out + w[t] * x_t
    return out


def old_fourier(sd, name: str, v: Tensor) -> Tensor:
    q = 2 * math.pi * v @ sd[f"{name}.B"]
    return torch.cat([v, q.sin(), q.cos()], dim=-1)


def old_generator(sd, p: str, cfg: dict, x_t, t, cond, r) -> Tensor:
    parts = [old_fourier(sd, f"{p}x_features", x_t), r]
    if cfg["cond_dim"]:
        parts.insert(1, old_fourier(sd, f"{p}c_features", cond))
    else:
        sd[f"{p}c_features.B"]  # noqa: B018 (an empty buffer, read to account for it)
    e = old_time_mlp(sd, f"{p}time_mlp.", timestep_embedding(t, cfg["time_dim"]))
    e = e + old_time_mlp(sd, f"{p}latent_mlp.", r)
    return old_body(sd, p, torch.cat(parts, -1), e)


def old_discriminator(sd, cfg: dict, x_prev, x_t, cond, t) -> Tensor:
    parts = [old_fourier(sd, "x_features", x_prev), old_fourier(sd, "x_features", x_t)]
    if cfg["cond_dim"]:
        parts.append(old_fourier(sd, "c_features", cond))
    else:
        sd["c_features.B"]  # noqa: B018
    e = old_time_mlp(sd, "time_mlp.", timestep_embedding(t, cfg["time_dim"]))
    act = lambda h: F.leaky_relu(h, 0.2)  # noqa: E731
    return old_body(sd, "", torch.cat(parts, -1), e, act=act, norm=False)[:, 0]


def old_camdm(sd, cfg: dict, x_t, t, past, style, traj) -> Tensor:
    """CAMDM with separate condition tokens (eq. 1): pre-LN encoder layers, GELU, final LN."""
    L, heads = cfg["latent"], cfg["heads"]
    e = old_time_mlp(sd, "time_embed.", timestep_embedding(t, L))
    conds = [e, sd["style_embed.weight"][style]]
    conds += [old_time_mlp(sd, "past_token.", past.flatten(1))]
    conds += [old_time_mlp(sd, "traj_token.", traj.flatten(1))]
    sd["null_past"]  # noqa: B018  (used only for a dropped past)
    h = torch.cat([torch.stack(conds, 1), _lin(sd, "frame_in", x_t)], 1) + sd["position"]
    B, n, _ = h.shape
    for i in range(cfg["layers"]):
        p = f"encoder.layers.{i}."
        a = _ln(sd, f"{p}norm1", h)
        q, k, v = F.linear(
            a, sd[f"{p}self_attn.in_proj_weight"], sd[f"{p}self_attn.in_proj_bias"]
        ).chunk(3, -1)
        split = lambda z: z.view(B, n, heads, L // heads).transpose(1, 2)  # noqa: E731
        w = torch.softmax(split(q) @ split(k).transpose(-1, -2) / math.sqrt(L // heads), -1)
        att = (w @ split(v)).transpose(1, 2).reshape(B, n, L)
        h = h + _lin(sd, f"{p}self_attn.out_proj", att)
        h = h + _lin(sd, f"{p}linear2", F.gelu(_lin(sd, f"{p}linear1", _ln(sd, f"{p}norm2", h))))
    h = _ln(sd, "encoder.norm", h)
    return _lin(sd, "frame_out", h[:, 4:])


def old_style_classifier(sd, x) -> tuple[Tensor, Tensor]:
    h = x.transpose(1, 2)
    for i, stride in ((0, 1), (2, 2), (4, 2)):
        h = F.gelu(F.conv1d(h, sd[f"convs.{i}.weight"], sd[f"convs.{i}.bias"], stride, 2))
    f = _lin(sd, "project", torch.cat([h.mean(-1), h.amax(-1)], -1))
    return f, _lin(sd, "head.2", F.gelu(f))


# ---- comparing a network with its reference ---------------------------------------------------


def _randn(g: torch.Generator, *shape: int) -> Tensor:
    return torch.randn(*shape, generator=g)


def compare(model: torch.nn.Module, prefix: str = "", sd: Recorder | None = None) -> Recorder:
    """Run ``model`` and the old code on fixed inputs; assert bit-identical outputs."""
    sd = sd if sd is not None else Recorder(model.state_dict())
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        if isinstance(model, MLPDenoiser):
            c = model.config
            x, cond = _randn(g, B, c.x_dim), _randn(g, B, c.cond_dim)
            t = torch.arange(B) % min(5, len(c.skip or c.skip_root or c.skip_yaw or range(5)))
            want = old_denoiser(sd, prefix, vars(c), x, t, cond if c.cond_dim else None)
            assert torch.equal(model(x, t, cond if c.cond_dim else None), want)
        elif isinstance(model, DDGANGenerator):
            c = model.config
            x, cond, r = _randn(g, B, c.x_dim), _randn(g, B, c.cond_dim), _randn(g, B, c.latent_dim)
            t = torch.arange(B) % 3
            cond = cond if c.cond_dim else None
            want = old_generator(sd, prefix, vars(c), x, t, cond, r)
            assert torch.equal(model(x, t, cond, r), want)
        elif isinstance(model, DDGANDiscriminator):
            c = model.config
            a, x, cond = _randn(g, B, c.x_dim), _randn(g, B, c.x_dim), _randn(g, B, c.cond_dim)
            t = torch.arange(B) % 3
            cond = cond if c.cond_dim else None
            assert torch.equal(model(a, x, cond, t), old_discriminator(sd, vars(c), a, x, cond, t))
        elif isinstance(model, MLPRegressor):
            cond = _randn(g, B, model.cond_dim)
            assert torch.equal(model(cond), old_sequential(sd, f"{prefix}net.", cond))
        elif isinstance(model, AAMDM):
            compare(model.generator, f"{prefix}generator.", sd)
            if model.polisher is not None:
                compare(model.polisher, f"{prefix}polisher.", sd)
        elif isinstance(model, AAMDMMotion):
            ae, c = model.autoencoder, model.config
            y, xz = _randn(g, B, c.y_dim), _randn(g, B, c.x_dim + c.z_dim)
            assert torch.equal(ae.encode(y), old_sequential(sd, "autoencoder.encoder.", y))
            assert torch.equal(ae.decode(xz), old_sequential(sd, "autoencoder.decoder.", xz))
            compare(model.transition, "transition.", sd)
            for name in ("y", "x", "xz"):  # the normalisation buffers
                sd[f"{name}_mean"], sd[f"{name}_std"]  # noqa: B018
        elif isinstance(model, PolicyNet):  # SB3's MlpPolicy actor: Linear, Tanh, ..., Linear
            obs = _randn(g, B, model.obs_dim)
            h, i = obs, 0
            while f"body.{i}.weight" in sd:
                h = torch.tanh(_lin(sd, f"body.{i}", h))
                i += 2
            assert torch.equal(model(obs), _lin(sd, "head", h))
            sd["log_std"]  # noqa: B018  (kept for sampling; the mean is the action)
        elif isinstance(model, CAMDM):  # torch's attention kernels: equal to rounding
            c = model.config
            x, past = _randn(g, B, c.future, c.dim), _randn(g, B, c.past, c.dim)
            traj, style, t = (
                _randn(g, B, c.future, 4),
                torch.arange(B) % c.n_styles,
                torch.arange(B),
            )
            want = old_camdm(sd, vars(c), x, t, past, style, traj)
            got = model(x, t, Conditions(past, style, traj))
            torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)
        elif isinstance(model, StyleClassifier):
            x = _randn(g, B, 59, model.config.in_dim)
            feats, logits = old_style_classifier(sd, x)
            assert torch.equal(model.features(x), feats) and torch.equal(model(x), logits)
        else:
            raise AssertionError(f"no reference for {type(model).__name__}")
    return sd


def _kind(f: Path) -> str:
    return json.loads(f.with_suffix(".json").read_text())["model"]["kind"]


def _shipped() -> list[Path]:
    files = sorted(CHECKPOINTS.glob("**/*.safetensors"))
    files = [f for f in files if not f.name.endswith(".train.safetensors")]
    return [f for f in files if _kind(f) != "mvae"]


SHIPPED = _shipped()


def test_every_shipped_checkpoint_is_covered():
    names = {f.parent.relative_to(CHECKPOINTS).as_posix() for f in SHIPPED if f.stem == "model"}
    assert {"amdm", "mse", "aamdm"} <= names
    assert any(f.parent.name == "aamdm_squ9" for f in SHIPPED)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.relative_to(CHECKPOINTS).as_posix())
def test_shipped_checkpoint_loads_strictly_and_computes_as_before(path):
    if path.stem == "model":  # the way the chapters load them
        ck = minimdm.pretrained(path.parent.relative_to(CHECKPOINTS).as_posix())
    else:
        ck = load_checkpoint(path)  # strict load_state_dict inside
    model = ck.model
    sd = compare(model)
    assert sd.read == set(model.state_dict()), "the old code and the network disagree on keys"


# Random networks of every kind, including those no shipped checkpoint holds (the discriminator)
# and options the shipped ones don't use (no condition, Fourier features, depth 2).
RANDOM = {
    "denoiser": lambda: MLPDenoiser(DenoiserConfig(6, 6, 16, 4, 8, "eps")),
    "denoiser_uncond_depth2": lambda: MLPDenoiser(DenoiserConfig(3, 0, 16, 2, 8, "x0")),
    "denoiser_skip": lambda: MLPDenoiser(
        DenoiserConfig(
            6, 6, 16, 3, 8, "x0", [0.9, 0.5, 0.1], None, [0.95, 0.7, 0.3], [1.0, 0.8, 0.5]
        )
    ),
    "regressor": lambda: MLPRegressor(4, 5, width=16, depth=3),
    "regressor_depth2": lambda: MLPRegressor(4, 5, width=16, depth=2),
    "generator": lambda: DDGANGenerator(GeneratorConfig(2, 2, 3, 16, 3, 8, fourier=4)),
    "generator_uncond": lambda: DDGANGenerator(GeneratorConfig(2, 0, 3, 16, 2, 8)),
    "discriminator": lambda: DDGANDiscriminator(DiscriminatorConfig(2, 2, 16, 3, 8, fourier=4)),
    "discriminator_uncond": lambda: DDGANDiscriminator(DiscriminatorConfig(2, 0, 16, 2, 8)),
    "camdm": lambda: CAMDM(CAMDMConfig(9, 3, 2, 4, latent=16, layers=2, heads=2, ff=32)),
    "style_classifier": lambda: StyleClassifier(ClassifierNetConfig(7, 3, 8, 4)),
}


@pytest.mark.parametrize("name", sorted(RANDOM))
def test_random_networks_compute_as_before(name):
    torch.manual_seed(0)
    model = RANDOM[name]().eval()
    for p in model.parameters():  # LayerNorms start at 1 and 0: make them count
        p.data.add_(0.1 * torch.randn_like(p))
    sd = compare(model)
    assert sd.read == set(model.state_dict())
