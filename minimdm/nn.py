"""The pieces every network and every trainer shares: the MLP body, the EMA, the learning rate.

* :class:`MLP` is the body of all six networks of the library (the A-MDM denoiser, the MSE
  regressor, the MVAE, the DD-GAN generator and discriminator, the pose autoencoder): fully
  connected layers, each followed by an activation and LayerNorm (A-MDM §3.2.1), with an
  optional input that reaches every layer (the time embedding of a denoiser, the latent of the
  MVAE decoder).
* :func:`ema_update` keeps the exponential moving average of a network's weights that the
  trainers sample with.
* :func:`cosine_lr` is the learning-rate schedule of every trainer: a linear warm-up, then a
  cosine decay (Loshchilov & Hutter 2017).
"""

from __future__ import annotations

import math
from collections.abc import Callable, MutableMapping, Sequence

import torch
from torch import Tensor, nn

__all__ = ["ACTIVATIONS", "MLP", "ema_update", "cosine_lr", "set_lr", "optimizer_step"]

ACTIVATIONS: dict[str, Callable[[], nn.Module]] = {
    "silu": nn.SiLU,  # A-MDM
    "mish": nn.Mish,  # AAMDM
    "leaky_relu": lambda: nn.LeakyReLU(0.2),  # GAN discriminators (DD-GAN)
}
"""The activations an :class:`MLP` can use, by name."""


class MLP(nn.Module):
    """``depth - 1`` blocks Linear → activation → LayerNorm, then a Linear output layer.

    ``forward(x, add=None, concat=None)`` maps ``x`` (B, in_dim) to (B, out_dim). Two optional
    inputs reach *every* layer, not only the first, so that the network cannot ignore them:

    * ``add`` (B, width) is added to every hidden layer before its activation: the time
      embedding :math:`e^t` of the A-MDM denoiser, or DD-GAN's level and latent embedding;
    * ``concat`` (B, concat_dim) is concatenated to the input of every layer, the output layer
      included: the latent z of the MVAE decoder.

    The parameters are ``input``, ``hidden.i``, ``norms.i`` and ``output``; a network that takes
    no per-layer input can use the same layers as an ``nn.Sequential`` (:meth:`sequential`).

    Args:
        in_dim, out_dim: sizes of the input and of the output.
        width: hidden units per layer.
        depth: Linear layers including the output layer (>= 2).
        activation: a name of :data:`ACTIVATIONS`: ``"silu"`` (A-MDM), ``"mish"`` (AAMDM) or
            ``"leaky_relu"`` (slope 0.2).
        norm: LayerNorm after every activation (False: none, as in a GAN discriminator).
        concat_dim: size of the ``concat`` input (0: none).
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        width: int,
        depth: int,
        activation: str = "silu",
        norm: bool = True,
        concat_dim: int = 0,
    ) -> None:
        super().__init__()
        if depth < 2:
            raise ValueError(f"depth must be >= 2 (one hidden and one output layer), got {depth}")
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
        self.activation, self.concat_dim, self.norm = activation, concat_dim, norm
        self.input = nn.Linear(in_dim + concat_dim, width)
        self.hidden = nn.ModuleList(nn.Linear(width + concat_dim, width) for _ in range(depth - 2))
        self.norms = nn.ModuleList(
            nn.LayerNorm(width) if norm else nn.Identity() for _ in range(depth - 1)
        )
        self.output = nn.Linear(width + concat_dim, out_dim)
        self.act = ACTIVATIONS[activation]()

    def forward(self, x: Tensor, add: Tensor | None = None, concat: Tensor | None = None) -> Tensor:
        if (concat is None) != (self.concat_dim == 0):
            raise ValueError(
                f"concat must be given exactly when concat_dim > 0 (concat_dim = "
                f"{self.concat_dim}), got {None if concat is None else tuple(concat.shape)}"
            )
        h = x
        for layer, norm in zip([self.input, *self.hidden], self.norms, strict=True):
            h = layer(h if concat is None else torch.cat([h, concat], dim=-1))  # (B, W)
            if add is not None:
                h = h + add
            h = norm(self.act(h))
        return self.output(h if concat is None else torch.cat([h, concat], dim=-1))

    def sequential(self) -> nn.Sequential:
        """The same layers as ``nn.Sequential(Linear, act, LayerNorm, ..., Linear)``.

        For networks without a per-layer input; its parameters are named ``0``, ``2``, ``3``, ...
        (``0``, ``2``, ``4``, ... without norms), as an ``nn.Sequential`` names them.
        """
        if self.concat_dim:
            raise ValueError("an MLP with a concat input cannot run as an nn.Sequential")
        layers: list[nn.Module] = []
        for layer, norm in zip([self.input, *self.hidden], self.norms, strict=True):
            layers += [layer, ACTIVATIONS[self.activation]()]
            if self.norm:
                layers.append(norm)
        return nn.Sequential(*layers, self.output)


@torch.no_grad()
def ema_update(
    average: nn.Module | MutableMapping[str, Tensor], model: nn.Module, decay: float, step: int
) -> float:
    """One step of the exponential moving average of ``model``'s weights, in place.

    :math:`\\bar\\theta \\leftarrow d\\,\\bar\\theta + (1 - d)\\,\\theta` for every parameter,
    with :math:`d = \\min(\\text{decay}, (1 + \\text{step}) / (10 + \\text{step}))`: the
    average warms up, following the raw weights closely during the first steps. Buffers are
    copied. ``decay = 0`` makes the average a copy of the model.

    Args:
        average: a network of the same architecture (e.g. a ``copy.deepcopy`` of ``model``) or
            a state dict of it.
        model: the network being trained.
        decay: the decay, in [0, 1).
        step: the optimizer steps done before this one (0-based).

    Returns the decay ``d`` used.
    """
    if not 0 <= decay < 1:
        raise ValueError(f"decay must lie in [0, 1), got {decay}")
    d = min(decay, (1 + step) / (10 + step))
    avg = average.state_dict() if isinstance(average, nn.Module) else average
    params = {name for name, _ in model.named_parameters()}
    for name, value in model.state_dict().items():
        if name not in avg:
            raise ValueError(f"the average has no entry {name!r}; it holds {sorted(avg)}")
        if name in params:
            avg[name].lerp_(value, 1 - d)
        else:
            avg[name].copy_(value)
    return d


def cosine_lr(
    step: int, total_steps: int, lr: float, lr_min: float = 0.0, warmup_steps: int = 0
) -> float:
    """The learning rate at ``step`` (0-based): linear warm-up, then cosine decay.

    During the first ``warmup_steps`` steps the rate rises linearly to ``lr``
    (``lr * (step + 1) / warmup_steps``); then it follows
    :math:`\\eta_{min} + \\tfrac12(\\eta - \\eta_{min})(1 + \\cos\\pi s)`, where ``s`` goes from
    0 at the first step after the warm-up to 1 at the last step, ``total_steps - 1``, and stays
    at 1 after it. ``lr_min = lr`` gives a constant rate.
    """
    if total_steps < 1 or warmup_steps < 0:
        raise ValueError(
            f"total_steps must be >= 1 and warmup_steps >= 0, got {total_steps}, {warmup_steps}"
        )
    if step < warmup_steps:
        return lr * (step + 1) / warmup_steps
    frac = min((step - warmup_steps) / max(total_steps - warmup_steps - 1, 1), 1.0)
    return lr_min + 0.5 * (lr - lr_min) * (1 + math.cos(math.pi * frac))


def set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Set the learning rate of every parameter group of ``optimizer``."""
    for group in optimizer.param_groups:
        group["lr"] = lr


def optimizer_step(
    optimizer: torch.optim.Optimizer,
    loss: Tensor,
    parameters: Sequence[nn.Parameter],
    grad_clip: float = 0.0,
    only_these: bool = False,
) -> None:
    """One gradient step: clear the gradients, back-propagate ``loss``, clip, step.

    ``parameters`` are those ``optimizer`` updates; ``grad_clip > 0`` clips their gradients'
    global norm. ``only_these`` back-propagates into them alone (a GAN's generator step must
    not leave gradients on the discriminator).
    """
    optimizer.zero_grad(set_to_none=True)
    loss.backward(inputs=list(parameters) if only_these else None)
    if grad_clip > 0:
        nn.utils.clip_grad_norm_(parameters, grad_clip)
    optimizer.step()
