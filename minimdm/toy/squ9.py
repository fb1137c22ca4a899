"""Squ-9: the 2D many-to-many transition toy of AAMDM (Qiao et al. 2024, §4.2, Figure 3).

A sequence of 2D points :math:`x_0, x_1, \\dots`. Each point lies in one of 9 isotropic Gaussians
("modes") whose centres form a 3x3 grid. The transition rule picks the next point's mode from the
current one:

* ``rule="other"`` (default, the paper's set-up): the next mode is uniform over the **other 8**
  modes, never the current one. The transition :math:`p(x_n | x_{n-1})` is therefore
  many-to-many (8 targets per source, each target reached from 8 sources) and depends on the
  current mode (the forbidden target moves with the source), so a model has to read
  :math:`x_{n-1}` *and* keep 8 separate modes alive.
* ``rule="neighbors"``: the next mode is uniform over the 2-4 grid neighbours (up, down, left,
  right) of the current one: a sparser, still multimodal rule, used in an exercise.

Within a mode the point is :math:`c_k + \\sigma\\,\\epsilon`, :math:`\\epsilon \\sim N(0, I)`.

Modes are numbered row-major: mode ``k`` sits at column ``k % 3`` and row ``k // 3``; mode 4 is
the centre ``(0, 0)``.

Metrics (:func:`squ9_metrics`) judge a model's transitions ``(x_prev, x_next)``; plots draw them.
The small trainers :func:`train_denoiser` and :func:`train_regressor` fit a conditional DDPM and
the MSE baseline on pairs; chapter 1 and ``benchmarks/squ9_steps.py`` use them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor, nn

from minimdm.diffusion import NoiseSchedule, check_finite, diffusion_loss
from minimdm.nn import cosine_lr, optimizer_step, set_lr

__all__ = [
    "Squ9",
    "squ9_metrics",
    "plot_transitions",
    "plot_transition_matrix",
    "train_denoiser",
    "train_regressor",
]

N_MODES = 9


@dataclass
class Squ9:
    """The Squ-9 set: 9 Gaussians on a 3x3 grid and a rule for the next point's mode."""

    spacing: float = 1.0
    """Distance between neighbouring grid centres; the centres are at {-1, 0, 1} * spacing."""
    sigma: float = 0.1
    """Standard deviation of each Gaussian (isotropic)."""
    rule: Literal["other", "neighbors"] = "other"
    """Transition rule: 'other' (uniform over the 8 other modes) or 'neighbors' (grid adjacent)."""

    def __post_init__(self) -> None:
        if not self.spacing > 0:
            raise ValueError(f"spacing must be > 0, got {self.spacing}")
        if not self.sigma > 0:
            raise ValueError(f"sigma must be > 0, got {self.sigma}")
        if self.rule not in ("other", "neighbors"):
            raise ValueError(f"rule must be 'other' or 'neighbors', got {self.rule!r}")

    @property
    def mode_centers(self) -> Tensor:
        """The 9 centres, row-major, shape (9, 2)."""
        g = torch.tensor([-1.0, 0.0, 1.0]) * self.spacing
        ys, xs = torch.meshgrid(g, g, indexing="ij")
        return torch.stack([xs.flatten(), ys.flatten()], dim=-1)  # (9, 2)

    def transition_matrix(self) -> Tensor:
        """The true mode-transition matrix P[i, j] = p(mode_n = j | mode_{n-1} = i), (9, 9)."""
        if self.rule == "other":
            P = (1.0 - torch.eye(N_MODES)) / (N_MODES - 1)
        else:
            rc = torch.stack([torch.arange(9) // 3, torch.arange(9) % 3], dim=-1)  # (9, 2)
            adjacent = (rc[:, None] - rc[None]).abs().sum(-1) == 1  # (9, 9)
            P = adjacent.float() / adjacent.sum(1, keepdim=True)
        return P

    def mode_of(self, x: Tensor) -> Tensor:
        """Index of the nearest centre for each point of ``x`` (..., 2) -> (...,) long."""
        c = self.mode_centers.to(x.device, x.dtype)
        return torch.cdist(x.reshape(-1, 2), c).argmin(-1).reshape(x.shape[:-1])

    def sample_modes(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """``n`` modes drawn uniformly from the 9, shape (n,)."""
        return torch.randint(0, N_MODES, (n,), generator=generator)

    def next_modes(self, modes: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Draw the next mode for each current mode (n,) by the transition rule."""
        P = self.transition_matrix()
        return torch.multinomial(P[modes], 1, generator=generator).squeeze(-1)  # (n,)

    def sample_points(self, modes: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """One point per mode: :math:`c_k + \\sigma\\epsilon`, (n,) -> (n, 2)."""
        noise = torch.randn(modes.shape[0], 2, generator=generator)
        return self.mode_centers[modes] + self.sigma * noise

    def posterior_x0(self, x_t: Tensor, x_prev: Tensor, alpha_bar: float | Tensor) -> Tensor:
        """The ideal denoiser: :math:`E[x_n \\mid x_n^t, x_{n-1}]` in closed form, (B, 2).

        With :math:`x^t = a x^0 + b\\epsilon`, :math:`a = \\sqrt{\\bar\\alpha_t}`,
        :math:`b^2 = 1-\\bar\\alpha_t`, each allowed target mode :math:`k` of the source's mode
        gives :math:`x^t \\sim \\mathcal N(a c_k, (a^2\\sigma^2 + b^2) I)`; the answer is the
        responsibility-weighted mean of :math:`c_k + \\frac{a\\sigma^2}{a^2\\sigma^2+b^2}(x^t - a
        c_k)`. It minimises the x0 loss: no network trained on Squ-9 can have a smaller error.
        """
        ab = torch.as_tensor(alpha_bar, dtype=x_t.dtype, device=x_t.device)
        a, b2, s2 = ab.sqrt(), 1 - ab, self.sigma**2
        c = self.mode_centers.to(x_t.device, x_t.dtype)  # (9, 2)
        allowed = self.transition_matrix().to(x_t.device)[self.mode_of(x_prev)] > 0  # (B, 9)
        var = a**2 * s2 + b2
        d2 = ((x_t[:, None] - a * c[None]) ** 2).sum(-1)  # (B, 9)
        logw = (-0.5 * d2 / var).masked_fill(~allowed, float("-inf"))
        w = logw.softmax(-1)  # (B, 9) p(k | x_t, x_prev)
        means = c[None] + (a * s2 / var) * (x_t[:, None] - a * c[None])  # (B, 9, 2)
        return (w[..., None] * means).sum(1)

    def sample_pairs(
        self, n: int, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor]:
        """``n`` transitions ``(x_prev, x_next)``, each (n, 2); source modes are uniform."""
        m_prev = self.sample_modes(n, generator)
        m_next = self.next_modes(m_prev, generator)
        return self.sample_points(m_prev, generator), self.sample_points(m_next, generator)

    def sample_sequence(
        self, length: int, n: int = 1, generator: torch.Generator | None = None
    ) -> Tensor:
        """``n`` ground-truth sequences of ``length`` points, shape (n, length, 2)."""
        if length < 1:
            raise ValueError(f"length must be >= 1, got {length}")
        modes = [self.sample_modes(n, generator)]
        for _ in range(length - 1):
            modes.append(self.next_modes(modes[-1], generator))
        m = torch.stack(modes, dim=1)  # (n, length)
        return self.sample_points(m.flatten(), generator).reshape(n, length, 2)


def squ9_metrics(
    x_prev: Tensor,
    x_next: Tensor,
    squ9: Squ9 | None = None,
    min_share: float = 1 / 32,
) -> dict[str, Any]:
    """Judge a model's transitions ``x_prev (N, 2) -> x_next (N, 2)`` against the Squ-9 rule.

    Each sample's source mode is the centre nearest ``x_prev``. Then:

    * ``precision``: the share of ``x_next`` within :math:`3\\sigma` of an *allowed* target mode
      of its source (for the default rule: any mode but its own). Ground truth scores
      :math:`1 - e^{-9/2} \\approx 0.989` (the 2D Gaussian mass inside radius :math:`3\\sigma`).
    * ``coverage_per_mode`` (9,): for each source mode, the fraction of its allowed targets that
      are *covered*, i.e. receive at least ``min_share`` of that source's samples inside their
      :math:`3\\sigma` disc (default 1/32: a quarter of the fair share 1/8, so that a few stray
      samples do not count as a mode). ``coverage`` is the mean over source modes that occur.
    * ``matrix`` (9, 9): the model's empirical mode-transition matrix, each ``x_next`` assigned
      to its nearest centre (blurred samples still land in a row, off-mode ones are what
      ``precision`` measures); rows sum to 1, rows of absent sources are NaN.
    * ``transition_tv``: the mean over source rows of the total-variation distance
      :math:`\\tfrac12\\sum_j |\\hat P_{ij} - P_{ij}|` to the true matrix, in [0, 1]; 0 is perfect,
      a model that always predicts the grid centre scores 0.89.

    Also returns ``tv_per_mode`` (9,) and ``counts`` (9,), the samples per source mode.
    """
    squ9 = squ9 or Squ9()
    if x_prev.shape != x_next.shape or x_prev.dim() != 2 or x_prev.shape[1] != 2:
        raise ValueError(
            f"x_prev and x_next must both have shape (N, 2), got {tuple(x_prev.shape)} "
            f"and {tuple(x_next.shape)}"
        )
    x_prev, x_next = x_prev.detach().float().cpu(), x_next.detach().float().cpu()
    check_finite("x_prev", x_prev)
    check_finite("x_next", x_next)
    P = squ9.transition_matrix()  # (9, 9)
    allowed = P > 0
    src = squ9.mode_of(x_prev)  # (N,)
    dist = torch.cdist(x_next, squ9.mode_centers)  # (N, 9)
    within = dist <= 3 * squ9.sigma  # (N, 9) inside the 3-sigma disc of each mode
    precise = (within & allowed[src]).any(-1)  # (N,)

    counts = torch.bincount(src, minlength=N_MODES).float()  # (9,)
    hits = torch.zeros(N_MODES, N_MODES)  # hits[i, j]: samples from i inside disc j
    hits.index_add_(0, src, within.float())
    share = hits / counts.clamp(min=1)[:, None]
    covered = (share >= min_share) & allowed
    coverage_per_mode = covered.sum(1).float() / allowed.sum(1).float()  # (9,)

    tgt = dist.argmin(-1)  # (N,)
    matrix = torch.zeros(N_MODES, N_MODES)
    matrix.index_put_((src, tgt), torch.ones(len(src)), accumulate=True)
    present = counts > 0
    matrix = matrix / counts[:, None]
    matrix[~present] = float("nan")
    tv = 0.5 * (matrix - P).abs().sum(1)  # (9,)

    return {
        "coverage": coverage_per_mode[present].mean().item(),
        "precision": precise.float().mean().item(),
        "transition_tv": tv[present].mean().item(),
        "coverage_per_mode": coverage_per_mode.numpy(),
        "tv_per_mode": tv.numpy(),
        "matrix": matrix.numpy(),
        "counts": counts.long().numpy(),
    }


# ----------------------------------------------------------------------------------------------
# Plots


def _axes(ax):
    import matplotlib.pyplot as plt

    if ax is None:
        fig, ax = plt.subplots(figsize=(4, 4))
        return fig, ax
    return ax.figure, ax


def plot_transitions(
    x_prev: Tensor,
    x_next: Tensor,
    ax=None,
    squ9: Squ9 | None = None,
    arrows: int = 0,
    title: str | None = None,
    s: float = 2.0,
):
    """Draw the 3x3 grid (3-sigma circles) and the sampled next points, coloured by source mode.

    ``arrows`` > 0 also draws that many ``x_prev -> x_next`` arrows. Returns the Figure.
    """
    import matplotlib.pyplot as plt

    squ9 = squ9 or Squ9()
    fig, ax = _axes(ax)
    x_prev, x_next = x_prev.detach().cpu().numpy(), x_next.detach().cpu().numpy()
    centers = squ9.mode_centers.numpy()
    for c in centers:
        ax.add_patch(plt.Circle(c, 3 * squ9.sigma, fill=False, lw=0.8, color="0.6"))
    src = squ9.mode_of(torch.as_tensor(x_prev)).numpy()
    ax.scatter(x_next[:, 0], x_next[:, 1], c=src, cmap="tab10", vmin=0, vmax=9, s=s, alpha=0.6)
    for i in range(min(arrows, len(x_prev))):
        ax.annotate(
            "",
            xy=x_next[i],
            xytext=x_prev[i],
            arrowprops=dict(arrowstyle="->", lw=0.6, color=plt.cm.tab10(src[i] / 9), alpha=0.8),
        )
    lim, ticks = 1.6 * squ9.spacing, [-squ9.spacing, 0, squ9.spacing]
    ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xticks=ticks, yticks=ticks)
    ax.set_xlabel("$x_1$ (Squ-9 units)", fontsize=8, labelpad=1)
    ax.set_ylabel("$x_2$", fontsize=8, labelpad=1)
    ax.tick_params(labelsize=7, length=2, pad=1)
    if title:
        ax.set_title(title, fontsize=9)
    return fig


def plot_transition_matrix(matrix, ax=None, title: str | None = None, vmax: float | None = None):
    """Heatmap of a 9x9 mode-transition matrix (rows: source, columns: target); returns Figure."""
    fig, ax = _axes(ax)
    m = np.asarray(matrix, dtype=float)
    im = ax.imshow(m, cmap="viridis", vmin=0, vmax=vmax or max(np.nanmax(m), 1e-6))
    ax.set(xticks=range(9), yticks=range(9), xlabel="next mode", ylabel="current mode")
    ax.tick_params(labelsize=7)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    if title:
        ax.set_title(title, fontsize=9)
    return fig


# ----------------------------------------------------------------------------------------------
# Trainers on (x_prev, x_next) pairs


def _batches(n: int, steps: int, batch_size: int, generator: torch.Generator | None):
    """Yield ``steps`` index batches drawn with replacement (on the generator's device)."""
    dev = generator.device if generator is not None else "cpu"
    for _ in range(steps):
        yield torch.randint(0, n, (batch_size,), generator=generator, device=dev)


def _fit(
    model: nn.Module,
    loss_fn,
    n: int,
    steps: int,
    batch_size: int,
    lr: float,
    generator: torch.Generator | None,
) -> list[float]:
    """Adam with a cosine-decayed learning rate, ``loss_fn(idx)`` on ``steps`` batches of
    indices into ``n`` pairs. Returns the loss of every step."""
    device = next(model.parameters()).device
    params = list(model.parameters())
    opt = torch.optim.Adam(params, lr=lr)
    history = []
    model.train()
    for step, idx in enumerate(_batches(n, steps, batch_size, generator)):
        set_lr(opt, cosine_lr(step, steps, lr))
        loss = loss_fn(idx.to(device))
        optimizer_step(opt, loss, params)
        history.append(loss.item())
    model.eval()
    return history


def train_denoiser(
    model: nn.Module,
    schedule: NoiseSchedule,
    x_prev: Tensor,
    x_next: Tensor,
    steps: int = 1500,
    batch_size: int = 512,
    lr: float = 2e-3,
    generator: torch.Generator | None = None,
) -> list[float]:
    """Fit a conditional denoiser :math:`p_\\theta(x_{n-1}, x_n^t, e^t)` with A-MDM eq. 3.

    ``x_next`` is the clean sample, ``x_prev`` the condition. Adam with a cosine-decayed
    learning rate. Data and schedule are moved to the model's device; ``generator`` (on that
    device) draws the batches, the steps and the noise. Returns the loss of every step.
    """
    device = next(model.parameters()).device
    x_prev, x_next, schedule = x_prev.to(device), x_next.to(device), schedule.to(device)
    predicts = getattr(model, "predicts", "eps")

    def loss_fn(idx: Tensor) -> Tensor:
        return diffusion_loss(model, schedule, x_next[idx], x_prev[idx], generator, predicts)[0]

    return _fit(model, loss_fn, len(x_next), steps, batch_size, lr, generator)


def train_regressor(
    model: nn.Module,
    x_prev: Tensor,
    x_next: Tensor,
    steps: int = 1500,
    batch_size: int = 512,
    lr: float = 2e-3,
    generator: torch.Generator | None = None,
) -> list[float]:
    """Fit the deterministic baseline ``x_next ~ model(x_prev)`` with MSE (same loop as above)."""
    device = next(model.parameters()).device
    x_prev, x_next = x_prev.to(device), x_next.to(device)

    def loss_fn(idx: Tensor) -> Tensor:
        return ((model(x_prev[idx]) - x_next[idx]) ** 2).mean()

    return _fit(model, loss_fn, len(x_next), steps, batch_size, lr, generator)
