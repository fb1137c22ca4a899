"""The policy network of a steering controller, registered as the checkpoint kind ``policy``.

Kept apart from the environments so that loading any checkpoint (``minimdm.pretrained``) can
rebuild a policy without importing stable-baselines3.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from minimdm.checkpoint import register_model_kind

__all__ = ["PolicyNet"]


class PolicyNet(nn.Module):
    """The policy's mean action: an MLP with tanh units, as SB3's ``MlpPolicy`` actor.

    ``log_std`` is the Gaussian's learnt log standard deviation per action dimension (kept for
    reference: the book acts with the mean, :meth:`act` can also sample).
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...] = (256, 256)) -> None:
        super().__init__()
        self.obs_dim, self.act_dim, self.hidden = int(obs_dim), int(act_dim), tuple(hidden)
        layers: list[nn.Module] = []
        d = self.obs_dim
        for h in self.hidden:
            layers += [nn.Linear(d, h), nn.Tanh()]
            d = h
        self.body = nn.Sequential(*layers)
        self.head = nn.Linear(d, self.act_dim)
        self.log_std = nn.Parameter(torch.zeros(self.act_dim), requires_grad=False)

    def forward(self, obs: Tensor) -> Tensor:
        """(B, obs_dim) -> (B, act_dim) mean action (before clipping to [-1, 1])."""
        if obs.dim() != 2 or obs.shape[1] != self.obs_dim:
            raise ValueError(f"obs must have shape (B, {self.obs_dim}), got {tuple(obs.shape)}")
        return self.head(self.body(obs))

    @torch.no_grad()
    def act(
        self, obs: Tensor, deterministic: bool = True, generator: torch.Generator | None = None
    ) -> Tensor:
        """Actions (B, act_dim) in [-1, 1]: the mean, or a Gaussian sample around it."""
        mean = self(obs)
        if not deterministic:
            noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
            mean = mean + self.log_std.exp() * noise
        return mean.clamp(-1.0, 1.0)

    def spec(self) -> dict[str, Any]:
        return {"obs_dim": self.obs_dim, "act_dim": self.act_dim, "hidden": list(self.hidden)}


register_model_kind(
    "policy",
    PolicyNet,
    lambda c: PolicyNet(c["obs_dim"], c["act_dim"], tuple(c["hidden"])),
    lambda m: m.spec(),
)
