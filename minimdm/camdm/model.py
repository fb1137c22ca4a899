"""The CAMDM denoiser :math:`\\hat x_0 = G(x_t, t; p, c_l, c_rv, c_ro)` (Chen et al. 2024, eq. 1).

A transformer encoder reads a sequence of tokens: first the *condition tokens*, then one token
per noisy future frame, and returns the clean future from the frame tokens. Separate condition
tokenization (SCT, §3.2) gives each condition its own tokenizer and its own token:

=====  ===========================================================================
token  from
=====  ===========================================================================
0      the diffusion step t (sinusoidal embedding, then an MLP)
1      the style label c_l (a learned embedding per style)
2      the past motion p, P frames (an MLP on the flattened frames)
3      the future trajectory c_rv, c_ro, F points (an MLP on the flattened points)
4..    the F noisy frames x_t (a linear map per frame)
=====  ===========================================================================

With ``tokens="past_frames"`` the past motion gets one token per frame (a linear map each, as
in the authors' code), so that tokens 2..P+1 hold the past and P+2 the trajectory: the last
pose then reaches the frame tokens unsqueezed.

Learned positions are added to every token. Two ablations of Table 3 are switches of
:class:`CAMDMConfig`: ``tokens="single"`` fuses all conditions into one token, as MDM does
(Ours w/o SCT), and ``backbone="mlp"`` replaces the transformer by an MLP on the whole
flattened input (Ours w/ MLP).

**Dropping a condition.** Classifier-free guidance needs the model without the past motion
(eq. 5), and the rejected alternative without the style. A dropped past motion is replaced by a
learned null motion ``(P, D)``, a dropped style by a learned null style; :class:`Conditions`
carries per-sample ``keep_past`` and ``keep_style`` flags.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import torch
from torch import Tensor, nn

from minimdm.amdm.models import timestep_embedding
from minimdm.checkpoint import register_model_kind
from minimdm.nn import MLP

__all__ = ["CAMDMConfig", "Conditions", "CAMDM", "N_COND_TOKENS"]

N_COND_TOKENS = 4
"""Condition tokens of the separate layout: step, style, past motion, trajectory."""


@dataclass
class CAMDMConfig:
    """Size and variant of a :class:`CAMDM` network."""

    dim: int
    """D = 3 + 6 J: one frame."""
    n_styles: int
    """Number of style labels."""
    past: int = 10
    """P: past frames (CAMDM: 10)."""
    future: int = 45
    """F: future frames (CAMDM: 45)."""
    latent: int = 256
    """Token width (CAMDM's code: 256)."""
    layers: int = 4
    """Transformer layers (CAMDM's code: 4), or MLP layers for backbone 'mlp'."""
    heads: int = 4
    """Attention heads."""
    ff: int = 1024
    """Feed-forward width of a transformer layer, or the width of the MLP backbone."""
    dropout: float = 0.1
    """Dropout in the transformer layers."""
    tokens: str = "separate"
    """'separate': one token per condition (SCT); 'single': one fused condition token (w/o
    SCT); 'past_frames': separate tokens, the past motion one per frame (the official code)."""
    backbone: str = "transformer"
    """'transformer' (CAMDM) or 'mlp' (the ablation Ours w/ MLP)."""

    def __post_init__(self) -> None:
        if self.tokens not in ("separate", "single", "past_frames"):
            raise ValueError(
                f"tokens must be 'separate', 'single' or 'past_frames', got {self.tokens!r}"
            )
        if self.backbone not in ("transformer", "mlp"):
            raise ValueError(f"backbone must be 'transformer' or 'mlp', got {self.backbone!r}")
        for name in ("dim", "n_styles", "past", "future", "latent", "layers", "heads", "ff"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.latent % self.heads:
            raise ValueError(f"latent {self.latent} must divide into {self.heads} heads")


@dataclass
class Conditions:
    """The conditions of eq. 1 for a batch of B windows, in normalized units."""

    past: Tensor
    """(B, P, D) the past motion p."""
    style: Tensor
    """(B,) long: the style label c_l."""
    traj: Tensor
    """(B, F, 4) the future trajectory: c_rv (x, y) and c_ro (cos, sin)."""
    keep_past: Tensor | None = None
    """(B,) bool: False replaces the past motion by the learned null (eq. 5); None keeps all."""
    keep_style: Tensor | None = None
    """(B,) bool: False replaces the style by the learned null style; None keeps all."""

    @property
    def batch(self) -> int:
        return self.past.shape[0]

    def without(self, what: str) -> Conditions:
        """The same conditions with ``what`` ('past' or 'style') dropped for every sample."""
        off = torch.zeros(self.batch, dtype=torch.bool, device=self.past.device)
        if what == "past":
            return replace(self, keep_past=off)
        if what == "style":
            return replace(self, keep_style=off)
        raise ValueError(f"what must be 'past' or 'style', got {what!r}")

    def cat(self, other: Conditions) -> Conditions:
        """Two batches as one (for one forward pass of both halves of eq. 5)."""

        def keep(c: Conditions, flag: Tensor | None) -> Tensor:
            if flag is None:
                return torch.ones(c.batch, dtype=torch.bool, device=c.past.device)
            return flag

        return Conditions(
            torch.cat([self.past, other.past]),
            torch.cat([self.style, other.style]),
            torch.cat([self.traj, other.traj]),
            torch.cat([keep(self, self.keep_past), keep(other, other.keep_past)]),
            torch.cat([keep(self, self.keep_style), keep(other, other.keep_style)]),
        )

    def repeat(self, n: int) -> Conditions:
        """Each sample ``n`` times in a row (B n samples)."""

        def rep(x: Tensor | None) -> Tensor | None:
            return None if x is None else x.repeat_interleave(n, 0)

        return Conditions(
            rep(self.past),
            rep(self.style),
            rep(self.traj),
            rep(self.keep_past),
            rep(self.keep_style),
        )


class CAMDM(nn.Module):
    """The CAMDM denoiser: ``forward(x_t, t, cond) -> x0_hat``, ``x_t`` (B, F, D), ``t`` (B,),
    ``cond`` a :class:`Conditions`; it predicts the clean future (eq. 1, x0-prediction)."""

    def __init__(self, config: CAMDMConfig) -> None:
        super().__init__()
        c = self.config = config
        L, D, P, F = c.latent, c.dim, c.past, c.future
        self.predicts = "x0"
        self.null_past = nn.Parameter(torch.zeros(P, D))  # the learned p = ∅ of eq. 5
        self.style_embed = nn.Embedding(c.n_styles + 1, L)  # the last row is the null style
        self.time_embed = MLP(L, L, L, depth=2, norm=False).sequential()
        if c.backbone == "mlp":
            width = c.ff
            self.time_to_width = nn.Linear(L, width)
            self.net = MLP(F * D + P * D + F * 4 + L, F * D, width, max(c.layers, 2))
            return
        if c.tokens == "separate":
            self.past_token = MLP(P * D, L, L, depth=2, norm=False).sequential()
            self.traj_token = MLP(F * 4, L, L, depth=2, norm=False).sequential()
            n_cond = N_COND_TOKENS
        elif c.tokens == "past_frames":
            self.past_token = nn.Linear(D, L)  # one token per past frame
            self.traj_token = MLP(F * 4, L, L, depth=2, norm=False).sequential()
            n_cond = N_COND_TOKENS - 1 + P
        else:
            self.cond_token = MLP(2 * L + P * D + F * 4, L, L, depth=2, norm=False).sequential()
            n_cond = 1
        self.n_cond = n_cond
        self.frame_in = nn.Linear(D, L)
        self.position = nn.Parameter(0.02 * torch.randn(n_cond + F, L))
        layer = nn.TransformerEncoderLayer(
            L, c.heads, c.ff, c.dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(
            layer, c.layers, norm=nn.LayerNorm(L), enable_nested_tensor=False
        )
        self.frame_out = nn.Linear(L, D)

    # ---- the conditions, with the nulls of dropped ones
    def _inputs(self, t: Tensor, cond: Conditions) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        c = self.config
        B = cond.batch
        past = cond.past
        if cond.keep_past is not None:
            keep = cond.keep_past.to(past.device)[:, None, None]
            past = torch.where(keep, past, self.null_past.expand(B, -1, -1))
        style = cond.style.long()
        if cond.keep_style is not None:
            style = torch.where(cond.keep_style.to(style.device), style, c.n_styles)
        t_emb = self.time_embed(timestep_embedding(t, c.latent))  # (B, L)
        return t_emb, self.style_embed(style), past.flatten(1), cond.traj.flatten(1)

    def tokens(self, x_t: Tensor, t: Tensor, cond: Conditions) -> Tensor:
        """The token sequence the encoder reads, positions added: (B, n_cond + F, L).

        Token i < n_cond is a condition token (module docstring), then one per frame.
        """
        if self.config.backbone != "transformer":
            raise ValueError("an MLP backbone has no tokens")
        t_emb, s_emb, past, traj = self._inputs(t, cond)
        if self.config.tokens == "separate":
            conds = torch.stack([t_emb, s_emb, self.past_token(past), self.traj_token(traj)], 1)
        elif self.config.tokens == "past_frames":
            frames = self.past_token(past.view(past.shape[0], self.config.past, -1))  # (B, P, L)
            ends = torch.stack([t_emb, s_emb], 1)
            conds = torch.cat([ends, frames, self.traj_token(traj)[:, None]], 1)
        else:
            conds = self.cond_token(torch.cat([t_emb, s_emb, past, traj], -1))[:, None]
        seq = torch.cat([conds, self.frame_in(x_t)], 1)  # (B, n + F, L)
        return seq + self.position

    def forward(self, x_t: Tensor, t: Tensor, cond: Conditions) -> Tensor:
        c = self.config
        if x_t.dim() != 3 or x_t.shape[1:] != (c.future, c.dim):
            raise ValueError(
                f"x_t must have shape (B, {c.future}, {c.dim}), got {tuple(x_t.shape)}"
            )
        if c.backbone == "mlp":
            t_emb, s_emb, past, traj = self._inputs(t, cond)
            h = torch.cat([x_t.flatten(1), past, traj, s_emb], -1)
            return self.net(h, add=self.time_to_width(t_emb)).view_as(x_t)
        h = self.encoder(self.tokens(x_t, t, cond))  # (B, n + F, L)
        return self.frame_out(h[:, self.n_cond :])  # (B, F, D)

    def config_dict(self) -> dict:
        return asdict(self.config)


register_model_kind("camdm", CAMDM, lambda c: CAMDM(CAMDMConfig(**c)), lambda m: m.config_dict())
