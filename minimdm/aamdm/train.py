"""Training AAMDM's two modules (AAMDM Algorithm 1): the polisher, then the DD-GAN.

Both trainers take **windows** ``(N, h + 1, D)`` of consecutive samples: frame 0 starts a
window and frames ``1..h`` are its targets. Squ-9 pairs are windows with ``h = 1``; motion
uses the embedded vectors xz of ``h + 1`` consecutive frames.

* :func:`train_polisher` (Algorithm 1 lines 7-18): the x0-predicting diffusion model
  :math:`G^{ADM}` rolls out over the window, each frame denoised from a random polishing level
  ``t < T_adm`` and conditioned on its own previous output, with the loss of eqs. 7-9
  (values plus velocities).
* :func:`train_ddgan` (lines 19-25): the generator and the discriminator, at random GAN levels
  ``t >= T_adm``, with the non-saturating losses of eqs. 11-12 and an R1 penalty on real pairs
  (Xiao et al. 2022, §3.3). The conditions are the polisher's rollout when a polisher is given
  (line 23), else the ground-truth previous frames.

**Two pair constructions** (``GANConfig.pairs``, drawn by :func:`draw_gan_pairs`). Algorithm 1
writes them as (line numbers of the paper's Algorithm 1; the library's level ``t`` is the
paper's ``t + 1``)::

    20: xz^{t,real}_{1:h} <- FD(x̂z^0_{1:h})        x̂z^0: the polisher's rollout, lines 8-15
    21: xz^{t+1}_{1:h}    <- FD(xz^t_{1:h})         one forward step
    22: r^{t+1} ~ N(0, I)
    23: x̂z^0_k <- G^GAN(xz^{t+1}_k, x̂z^0_{k-1}, r^{t+1}, t+1)   for k in [1, h]
    24: xz^{t,fake}_{1:h} <- FD(x̂z^0_{1:h})        x̂z^0: now the generator's

* ``"paper"``: Algorithm 1 as written. The real pair forward-diffuses the **polisher's output**
  (line 20, then line 21), the fake :math:`x^{t-1}` forward-diffuses the **generator's**
  :math:`\\hat x^0` from clean, :math:`q(x^{t-1} | \\hat x^0)` (line 24), independently of
  :math:`x^t`. The paper is not consistent here: §3.3's prose says real pairs are "diffused
  from the original data", and eq. 12 takes the fake expectation over
  :math:`p(x^{t-1} | x^t, x_{n-1})`, a step conditioned on :math:`x^t` as DD-GAN's posterior
  draw is. ``"paper"`` follows the algorithm. The sampler
  (:func:`~minimdm.aamdm.model.aamdm_sample`) steps through the posterior either way.
* ``"ddgan"`` (the default, after Xiao et al. 2022, §3.3-3.4): real pairs forward-diffuse the
  **data**, and the fake :math:`x^{t-1}` is drawn from the **posterior**
  :math:`q(x^{t-1} | x^t, \\hat x^0)`, so the fake pair shares :math:`x^t` through the posterior
  as the sampler does.

Departures from the paper, each an option: ``GANConfig.r1_gamma`` (the paper names no R1
penalty; DD-GAN uses one), ``optimizer`` (the paper trains every network with RAdam, §4
"Implementation Details"; the default here is Adam), the activation of the networks
(``activation`` of :class:`~minimdm.aamdm.nets.GeneratorConfig` and
:class:`~minimdm.aamdm.nets.DiscriminatorConfig`; the paper's Figure 4 uses Mish everywhere), and
the training order: Algorithm 1 updates the polisher and the GAN in one loop, the library trains
the polisher first and then the GAN against the frozen polisher.

GAN training can diverge. Every ``ckpt_interval`` steps the trainer writes a checkpoint with
:func:`minimdm.checkpoint.save_checkpoint` (atomic), and a non-finite loss stops the run with a
:class:`GANDivergedError` that names the step, the losses and the last good checkpoint, which is
left untouched. A run resumes from its training state.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor, nn

from minimdm.aamdm.model import (
    DDGANDiscriminator,
    DDGANGenerator,
    q_posterior_sample,
    q_sample_pairs,
)
from minimdm.checkpoint import checkpoint_paths, load_train_state, save_checkpoint
from minimdm.diffusion import NoiseSchedule, q_sample
from minimdm.files import RunLock
from minimdm.nn import cosine_lr, ema_update, optimizer_step, set_lr

__all__ = [
    "PAIRS",
    "OPTIMIZERS",
    "GANDivergedError",
    "PolishConfig",
    "GANConfig",
    "GANPairs",
    "draw_gan_pairs",
    "polisher_rollout",
    "polish_loss",
    "discriminator_loss",
    "generator_loss",
    "train_polisher",
    "train_ddgan",
    "pairs_to_windows",
]


PAIRS = ("ddgan", "paper")
"""How real and fake pairs are made (see the module docstring): Xiao et al. or Algorithm 1."""
OPTIMIZERS = ("adam", "radam")
"""The optimizers a trainer can use (the paper: RAdam)."""


def _check_choice(name: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


def _optimizer(kind: str, params, lr: float, betas: tuple[float, float] = (0.9, 0.999)):
    """Adam or RAdam (Liu et al. 2020, the paper's choice) with the same betas."""
    _check_choice("optimizer", kind, OPTIMIZERS)
    cls = torch.optim.RAdam if kind == "radam" else torch.optim.Adam
    return cls(params, lr=lr, betas=betas)


class GANDivergedError(FloatingPointError):
    """A DD-GAN loss became NaN or Inf; the message names the step and the last good checkpoint."""


@dataclass
class PolishConfig:
    """Training of the polishing module (AAMDM §3.2, Algorithm 1 lines 7-18)."""

    steps: int = 2000
    """Optimizer steps."""
    batch_size: int = 256
    """Windows per step."""
    lr: float = 3e-3
    """Adam learning rate at the start, cosine-decayed to lr / 20 (paper: RAdam, 3e-4)."""
    w_vel: float = 1.0
    """Weight of the velocity loss, eq. 8 (w_val is 1)."""
    backprop_rollout: bool = True
    """Let gradients flow through the rollout's conditions (False: detach them)."""
    grad_clip: float = 1.0
    """Clip the gradient norm (0: no clipping)."""
    seed: int = 0
    """Seeds the batches and the noise."""
    optimizer: str = "adam"
    """'adam' or 'radam' (the paper: RAdam for every network, §4)."""

    def __post_init__(self) -> None:
        _check_choice("optimizer", self.optimizer, OPTIMIZERS)


@dataclass
class GANConfig:
    """Training of the DD-GAN generation module (AAMDM §3.3, eqs. 11-12)."""

    steps: int = 3000
    """Optimizer steps (each updates the discriminator, then the generator against it)."""
    batch_size: int = 256
    """Windows per step."""
    lr_g: float = 1e-3
    """Generator learning rate (Adam, betas 0.5 / 0.9 as DD-GAN; paper: RAdam, 1e-4)."""
    lr_d: float = 1e-3
    """Discriminator learning rate."""
    lr_end: float = 0.1
    """Both learning rates decay (cosine) to this fraction of their start (1: constant)."""
    r1_gamma: float = 0.05
    """Weight of the R1 penalty on real pairs (Xiao et al. 2022; 0: none, as in the paper)."""
    grad_clip: float = 5.0
    """Clip the gradient norms (0: no clipping)."""
    ema_decay: float = 0.999
    """Exponential moving average of the generator's weights, used for sampling (0: none)."""
    ckpt_interval: int = 500
    """Write a checkpoint every this many steps when a path is given (0: only at the end)."""
    seed: int = 0
    """Seeds the batches, levels and noise."""
    pairs: str = "ddgan"
    """'ddgan' (data real pairs, posterior fakes; Xiao et al.) or 'paper' (Algorithm 1 lines
    20-24: the polisher's output diffused for real pairs, the generator's x0 diffused for
    fakes)."""
    optimizer: str = "adam"
    """'adam' or 'radam' (the paper: RAdam), both with betas 0.5 / 0.9."""

    def __post_init__(self) -> None:
        _check_choice("pairs", self.pairs, PAIRS)
        _check_choice("optimizer", self.optimizer, OPTIMIZERS)


def pairs_to_windows(x_prev: Tensor, x_next: Tensor) -> Tensor:
    """Pairs ``(N, D)`` and ``(N, D)`` as windows ``(N, 2, D)`` (h = 1)."""
    if x_prev.shape != x_next.shape or x_prev.dim() != 2:
        raise ValueError(
            f"x_prev and x_next must both be (N, D), got {tuple(x_prev.shape)}, "
            f"{tuple(x_next.shape)}"
        )
    return torch.stack([x_prev, x_next], dim=1)


def _check_windows(windows: Tensor) -> None:
    if windows.dim() != 3 or windows.shape[1] < 2:
        raise ValueError(f"windows must have shape (N, h + 1 >= 2, D), got {tuple(windows.shape)}")
    if not torch.isfinite(windows).all():
        raise ValueError("windows must be finite, but they hold NaN/Inf")


def _levels(n: int, lo: int, hi: int, gen: torch.Generator, device) -> Tensor:
    return torch.randint(lo, hi, (n,), generator=gen, device=device)


def _draw(n: int, windows: Tensor, weights: Tensor | None, gen: torch.Generator) -> Tensor:
    """``n`` windows drawn with replacement: uniformly, or by ``weights`` (W,) when given."""
    if weights is None:
        return windows[_levels(n, 0, windows.shape[0], gen, windows.device)]
    return windows[torch.multinomial(weights, n, replacement=True, generator=gen)]


def _check_weights(weights: Tensor | None, windows: Tensor) -> Tensor | None:
    if weights is None:
        return None
    weights = torch.as_tensor(weights, dtype=torch.float64, device=windows.device)
    if weights.shape != (windows.shape[0],):
        want, got = windows.shape[0], tuple(weights.shape)
        raise ValueError(f"weights must have shape ({want},), one per window, got {got}")
    if not (torch.isfinite(weights).all() and (weights >= 0).all() and weights.sum() > 0):
        raise ValueError("weights must be finite, non-negative and not all zero")
    return weights


def polisher_rollout(
    polisher: nn.Module,
    schedule: NoiseSchedule,
    windows: Tensor,
    T_adm: int,
    generator: torch.Generator | None,
    detach: bool = False,
) -> Tensor:
    """Algorithm 1 lines 8-15: :math:`\\hat x^0_{1:h}` (B, h, D) along windows (B, h + 1, D).

    Frame ``n`` is noised to a random level ``t < T_adm`` and denoised by
    :math:`G^{ADM}(x_n^t, \\hat x^0_{n-1}, t)`, starting from the ground-truth frame 0.
    """
    B, n1, _ = windows.shape
    cond, out = windows[:, 0], []
    for n in range(1, n1):
        t = _levels(B, 0, T_adm, generator, windows.device)
        x_t = q_sample(schedule, windows[:, n], t, generator=generator)
        x0_hat = polisher(x_t, t, cond)  # (B, D)
        out.append(x0_hat)
        cond = x0_hat.detach() if detach else x0_hat
    return torch.stack(out, dim=1)


def polish_loss(
    x0_hat: Tensor, windows: Tensor, w_vel: float = 1.0, vel_dims: slice | None = None
) -> tuple[Tensor, dict[str, float]]:
    """AAMDM eqs. 7-9 on a rollout ``x0_hat`` (B, h, D) of windows (B, h + 1, D).

    :math:`L_{val} = \\|\\hat x_{1:h} - x_{1:h}\\|^2` and
    :math:`L_{vel} = \\|(\\hat x_{1:h} - \\hat x_{0:h-1}) - (x_{1:h} - x_{0:h-1})\\|^2` with
    :math:`\\hat x_0 = x_0`, each a mean over frames and dimensions (squared norms, velocities
    per frame); ``vel_dims`` restricts the velocity term to the engineered features x.
    """
    target = windows[:, 1:]
    l_val = ((x0_hat - target) ** 2).mean()
    prev_hat = torch.cat([windows[:, :1], x0_hat[:, :-1]], dim=1)
    v_hat, v = x0_hat - prev_hat, target - windows[:, :-1]  # (B, h, D)
    if vel_dims is not None:
        v_hat, v = v_hat[..., vel_dims], v[..., vel_dims]
    l_vel = ((v_hat - v) ** 2).mean()
    return l_val + w_vel * l_vel, {"l_val": float(l_val.detach()), "l_vel": float(l_vel.detach())}


def train_polisher(
    polisher: nn.Module,
    schedule: NoiseSchedule,
    windows: Tensor,
    T_adm: int,
    config: PolishConfig | None = None,
    vel_dims: slice | None = None,
    weights: Tensor | None = None,
) -> list[dict]:
    """Fit :math:`G^{ADM}` on the polishing levels ``0 .. T_adm - 1`` (Algorithm 1).

    ``weights`` (W,): how often each window is drawn (None: uniformly).
    Returns one record per step (``loss``, ``l_val``, ``l_vel``).
    """
    config = config or PolishConfig()
    _check_windows(windows)
    if not 1 <= T_adm <= schedule.T:
        raise ValueError(f"T_adm must lie in [1, T={schedule.T}] to train a polisher, got {T_adm}")
    device = next(polisher.parameters()).device
    windows, schedule = windows.to(device), schedule.to(device)
    weights = _check_weights(weights, windows)
    gen = torch.Generator(device).manual_seed(config.seed)
    opt = _optimizer(config.optimizer, polisher.parameters(), config.lr)
    history = []
    polisher.train()
    for step in range(config.steps):
        set_lr(opt, cosine_lr(step, config.steps, config.lr, config.lr / 20))
        w = _draw(config.batch_size, windows, weights, gen)
        x0_hat = polisher_rollout(
            polisher, schedule, w, T_adm, gen, detach=not config.backprop_rollout
        )
        loss, info = polish_loss(x0_hat, w, config.w_vel, vel_dims)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"polisher loss became {loss.item()} at step {step}")
        optimizer_step(opt, loss, list(polisher.parameters()), config.grad_clip)
        history.append({"step": step + 1, "loss": loss.item(), **info})
    polisher.eval()
    return history


class GANPairs(NamedTuple):
    """One batch of the DD-GAN game, every tensor flattened over windows and frames (B*h, ...)."""

    k: Tensor
    """(B*h,) the GAN's own step index; the level is ``t = k + T_adm``."""
    cond: Tensor
    """(B*h, C) the conditions x_{n-1} (the polisher's rollout or the data, line 23)."""
    x0_real: Tensor
    """(B*h, D) what the real pairs diffuse: the data ('ddgan') or the polisher's output."""
    x_prev_real: Tensor
    """(B*h, D) the real x^{t-1} (line 20)."""
    x_t: Tensor
    """(B*h, D) x^t, one forward step from the real x^{t-1} (line 21); the generator's input."""
    x0_fake: Tensor
    """(B*h, D) the generator's clean estimate (line 23)."""
    x_prev_fake: Tensor
    """(B*h, D) the fake x^{t-1}: posterior ('ddgan') or forward diffusion (line 24)."""


def draw_gan_pairs(
    gan: nn.Module,
    schedule: NoiseSchedule,
    windows: Tensor,
    T_gan: int,
    generator: torch.Generator | None = None,
    pairs: str = "ddgan",
    polisher: nn.Module | None = None,
    T_adm: int | None = None,
) -> GANPairs:
    """Real and fake pairs for one batch of windows (B, h + 1, D), AAMDM Algorithm 1 lines 19-24.

    ``pairs="paper"`` follows the algorithm as written:

    * line 20, ``xz^{t,real}_{1:h} <- FD(x̂z^0_{1:h})``: the real :math:`x^{t-1}` is drawn from
      :math:`q(x^{t-1} | \\hat x^0_{ADM})`, the forward diffusion of the **polisher's rollout**
      of lines 8-15 (:func:`polisher_rollout`), not of the data;
    * line 21, ``xz^{t+1}_{1:h} <- FD(xz^t_{1:h})``: :math:`x^t` one forward step from it;
    * line 23, ``x̂z^0_k <- G^GAN(xz^{t+1}_k, x̂z^0_{k-1}, r^{t+1}, t+1) for k in [1, h]``: the
      conditions are the polisher's rollout shifted by one frame, frame 0 the data (line 9; we
      read the "for k" as one batched assignment whose right side is the rollout);
    * line 24, ``xz^{t,fake}_{1:h} <- FD(x̂z^0_{1:h})``: the fake :math:`x^{t-1}` is drawn
      from :math:`q(x^{t-1} | \\hat x^0_{GAN})`, the forward diffusion of the **generator's**
      estimate, independently of :math:`x^t` given it.

    With ``T_adm = 0`` there is no polisher, and the data stand in for its output.

    ``pairs="ddgan"`` (Xiao et al. 2022) diffuses the data for the real pairs and draws the fake
    :math:`x^{t-1} \\sim q(x^{t-1} | x^t, \\hat x^0_{GAN})` (the posterior, as the sampler
    does); its conditions are the polisher's rollout when a polisher is given and h > 1, else
    the data.

    Levels are drawn uniformly over the GAN's ``T_gan`` levels of ``schedule`` (the top ones).
    The rollout runs without gradients; the generator's output keeps its graph.
    """
    _check_choice("pairs", pairs, PAIRS)
    T = schedule.T
    T_adm = T - T_gan if T_adm is None else T_adm
    if pairs == "paper" and T_adm > 0 and polisher is None:
        raise ValueError(
            "pairs='paper' diffuses the polisher's output (Algorithm 1 line 20): pass the "
            f"trained polisher (T_adm = {T_adm}), or use pairs='ddgan'"
        )
    B, n1, D = windows.shape
    roll = None
    if polisher is not None and T_adm > 0 and (pairs == "paper" or n1 > 2):
        with torch.no_grad():
            polisher.eval()
            roll = polisher_rollout(polisher, schedule, windows, T_adm, generator)  # (B, h, D)
    if roll is not None:
        cond = torch.cat([windows[:, :1], roll[:, :-1]], dim=1)  # (B, h, D)
    else:
        cond = windows[:, :-1]
    x0 = roll if pairs == "paper" and roll is not None else windows[:, 1:]
    x0 = x0.reshape(B * (n1 - 1), D)
    cond = cond.reshape(B * (n1 - 1), -1)
    k = _levels(x0.shape[0], 0, T_gan, generator, x0.device)  # the GAN's own step index
    t = k + (T - T_gan)
    x_prev_real, x_t = q_sample_pairs(schedule, x0, t, generator)  # lines 20-21
    r = torch.randn((x0.shape[0], gan.config.latent_dim), generator=generator, device=x0.device)
    x0_fake = gan(x_t, k, cond, r)  # lines 22-23
    if pairs == "paper":
        x_prev_fake = q_sample(schedule, x0_fake, t - 1, generator=generator)  # line 24
    else:
        x_prev_fake = q_posterior_sample(schedule, x0_fake, x_t, t, generator)
    return GANPairs(k, cond, x0, x_prev_real, x_t, x0_fake, x_prev_fake)


def discriminator_loss(
    disc: DDGANDiscriminator,
    x_prev_real: Tensor,
    x_prev_fake: Tensor,
    x_t: Tensor,
    cond: Tensor | None,
    k: Tensor,
    r1_gamma: float = 0.0,
) -> tuple[Tensor, dict[str, float]]:
    """AAMDM eq. 12 with a logit D: :math:`\\mathrm{softplus}(-D_r) + \\mathrm{softplus}(D_f)`.

    ``r1_gamma`` adds the R1 penalty :math:`\\tfrac{\\gamma}{2}\\|\\nabla_{x^{t-1}} D_r\\|^2`
    (Xiao et al. 2022). The fake pair is detached: this loss trains D only.
    """
    x_prev_real = x_prev_real.detach().requires_grad_(r1_gamma > 0)
    d_real = disc(x_prev_real, x_t, cond, k)
    d_fake = disc(x_prev_fake.detach(), x_t, cond, k)
    loss = nn.functional.softplus(-d_real).mean() + nn.functional.softplus(d_fake).mean()
    r1 = torch.zeros((), device=x_t.device)
    if r1_gamma > 0:
        (grad,) = torch.autograd.grad(d_real.sum(), x_prev_real, create_graph=True)
        r1 = grad.pow(2).flatten(1).sum(1).mean()
        loss = loss + 0.5 * r1_gamma * r1
    info = {
        "loss_d": loss.item(),
        "d_real": torch.sigmoid(d_real).mean().item(),
        "d_fake": torch.sigmoid(d_fake).mean().item(),
        "r1": r1.item(),
    }
    return loss, info


def generator_loss(
    disc: DDGANDiscriminator, x_prev_fake: Tensor, x_t: Tensor, cond: Tensor | None, k: Tensor
) -> Tensor:
    """AAMDM eq. 11, non-saturating: :math:`\\mathrm{softplus}(-D(\\text{fake pair}))`."""
    return nn.functional.softplus(-disc(x_prev_fake, x_t, cond, k)).mean()


@dataclass
class _GANRun:
    """What a DD-GAN run carries from step to step, and what its checkpoints save."""

    opt_g: torch.optim.Optimizer
    """The generator's optimizer."""
    opt_d: torch.optim.Optimizer
    """The discriminator's optimizer."""
    gen: torch.Generator
    """The one source of randomness: batches, levels, latents and noise."""
    ema: dict[str, Tensor]
    """The averaged generator weights (what sampling and checkpoints use)."""
    step: int = 0
    """Steps done (the step a resumed run continues from)."""
    last_good: int | None = None
    """The step of the last checkpoint written (None: none yet)."""


def _check_ddgan_run(
    windows: Tensor,
    schedule: NoiseSchedule,
    T_gan: int,
    T_adm: int | None,
    config: GANConfig,
    polisher: nn.Module | None,
) -> int:
    """Refuse a run whose levels or pairs cannot work; return ``T_adm`` (default ``T - T_gan``)."""
    _check_windows(windows)
    if not 1 <= T_gan <= schedule.T:
        raise ValueError(f"T_gan must lie in [1, T={schedule.T}], got {T_gan}")
    T_adm = schedule.T - T_gan if T_adm is None else T_adm
    if T_gan + T_adm != schedule.T:
        raise ValueError(
            f"T_gan + T_adm must equal the schedule's T = {schedule.T}, got {T_gan} + {T_adm}"
        )
    if config.pairs == "paper" and T_adm > 0 and polisher is None:
        raise ValueError(
            "GANConfig.pairs='paper' diffuses the polisher's output (Algorithm 1 line 20): pass "
            f"polisher= (trained, T_adm = {T_adm}), or use pairs='ddgan'"
        )
    return T_adm


def _run_lock(checkpoint: str | Path | None) -> contextlib.AbstractContextManager:
    """The run lock of the checkpoint's folder (:class:`~minimdm.files.RunLock`), or none."""
    if checkpoint is None:
        return contextlib.nullcontext()
    return RunLock(checkpoint_paths(checkpoint).weights.parent)


def _start_ddgan(
    gan: DDGANGenerator,
    disc: DDGANDiscriminator,
    config: GANConfig,
    device: torch.device,
    bundle: nn.Module,
    checkpoint: str | Path | None,
) -> _GANRun:
    """Optimizers (betas 0.5 / 0.9, as DD-GAN), the seeded generator and the average; with a
    ``checkpoint`` that holds a training state, all of them (and the networks) restored from it.
    Both networks are left in training mode."""
    run = _GANRun(
        opt_g=_optimizer(config.optimizer, gan.parameters(), config.lr_g, (0.5, 0.9)),
        opt_d=_optimizer(config.optimizer, disc.parameters(), config.lr_d, (0.5, 0.9)),
        gen=torch.Generator(device).manual_seed(config.seed),
        ema={k: v.detach().clone() for k, v in gan.state_dict().items()},
    )
    gan.train()
    disc.train()
    if checkpoint is None or not checkpoint_paths(checkpoint).train.exists():
        return run
    _, state = load_train_state(checkpoint)
    bundle.load_state_dict(state["bundle"])
    gan.load_state_dict(state["gan_raw"])
    run.ema = {k: v.to(device) for k, v in state["gan_ema"].items()}
    disc.load_state_dict(state["disc"])
    run.opt_g.load_state_dict(state["opt_g"])
    run.opt_d.load_state_dict(state["opt_d"])
    run.gen.set_state(state["generator"].to(torch.uint8))
    run.step = run.last_good = int(state["step"])
    return run


def _save_ddgan(
    checkpoint: str | Path,
    bundle: nn.Module,
    gan: DDGANGenerator,
    disc: DDGANDiscriminator,
    run: _GANRun,
    metadata: dict | None,
    config: GANConfig,
) -> None:
    """Write ``bundle`` with the averaged generator and the training state to resume from; the
    run's last good checkpoint is now this one."""
    raw = {k: v.detach().clone() for k, v in gan.state_dict().items()}
    gan.load_state_dict(run.ema)  # the checkpoint samples with the averaged generator
    state = {
        "step": run.step,
        "bundle": bundle.state_dict(),
        "gan_raw": raw,
        "gan_ema": run.ema,
        "disc": disc.state_dict(),
        "opt_g": run.opt_g.state_dict(),
        "opt_d": run.opt_d.state_dict(),
        "generator": run.gen.get_state(),
    }
    meta = {**(metadata or {}), "step": run.step, "gan_config": asdict(config)}
    try:
        save_checkpoint(checkpoint, bundle, meta, optimizer_state=state)
    finally:
        gan.load_state_dict(raw)
    run.last_good = run.step


def _checkpoint_due(step: int, config: GANConfig) -> bool:
    """A checkpoint at the end and every ``config.ckpt_interval`` steps (if not 0)."""
    return step == config.steps or bool(config.ckpt_interval and step % config.ckpt_interval == 0)


def _diverged(
    step: int,
    loss_d: Tensor,
    loss_g: Tensor,
    checkpoint: str | Path | None,
    last_good: int | None,
) -> GANDivergedError:
    """The error for a non-finite loss at ``step``, naming the last good checkpoint."""
    where = (
        f"the last good checkpoint (step {last_good}) is kept at "
        f"{checkpoint_paths(checkpoint).weights}"
        if checkpoint is not None and last_good is not None
        else "no checkpoint was written (pass checkpoint= to keep one)"
    )
    return GANDivergedError(
        f"DD-GAN training diverged at step {step}: loss_D = {loss_d.item()}, "
        f"loss_G = {loss_g.item()}; {where}. Lower lr_g / lr_d or raise r1_gamma."
    )


def train_ddgan(
    gan: DDGANGenerator,
    disc: DDGANDiscriminator,
    schedule: NoiseSchedule,
    windows: Tensor,
    T_gan: int,
    config: GANConfig | None = None,
    polisher: nn.Module | None = None,
    T_adm: int | None = None,
    checkpoint: str | Path | None = None,
    bundle: nn.Module | None = None,
    metadata: dict | None = None,
    resume: bool = True,
    callback=None,
    weights: Tensor | None = None,
) -> list[dict]:
    """Train the DD-GAN generation module on ``windows`` (N, h + 1, D).

    Args:
        gan, disc: the generator (trained) and discriminator.
        schedule: the full ``T_gan + T_adm`` schedule; the GAN owns its top ``T_gan`` levels.
        polisher: if given (and ``T_adm`` > 0), the conditions are its rollout along each window
            (Algorithm 1 line 23), else the ground-truth previous frames. ``config.pairs =
            "paper"`` needs it: the real pairs diffuse its output (line 20; see
            :func:`draw_gan_pairs`).
        checkpoint: a folder or stem; ``bundle`` (the module holding ``gan``, default ``gan``)
            is saved there every ``config.ckpt_interval`` steps and at the end, with the
            discriminator and optimizers as training state. With ``resume`` a run continues
            from that state.
        callback: ``callback(step, record)`` after every step (``record["ema"]`` holds the
            averaged generator weights); raising stops the run.
        weights: (N,) how often each window is drawn (None: uniformly).

    At the end ``gan`` holds the averaged weights (``config.ema_decay``), as do checkpoints.

    Raises:
        GANDivergedError: a loss became NaN or Inf. Nothing is written after the last good
            checkpoint, whose step and path the message names.

    Returns one record per step (losses, discriminator outputs, seconds).
    """
    config = config or GANConfig()
    T_adm = _check_ddgan_run(windows, schedule, T_gan, T_adm, config, polisher)
    with _run_lock(checkpoint):  # one run per checkpoint folder
        device = next(gan.parameters()).device
        windows, schedule = windows.to(device), schedule.to(device)
        weights = _check_weights(weights, windows)
        bundle = bundle if bundle is not None else gan
        run = _start_ddgan(gan, disc, config, device, bundle, checkpoint if resume else None)
        history: list[dict] = []
        t0 = time.perf_counter()
        while run.step < config.steps:
            for opt, lr in ((run.opt_g, config.lr_g), (run.opt_d, config.lr_d)):
                set_lr(opt, cosine_lr(run.step, config.steps, lr, lr * config.lr_end))
            w = _draw(config.batch_size, windows, weights, run.gen)
            p = draw_gan_pairs(gan, schedule, w, T_gan, run.gen, config.pairs, polisher, T_adm)
            loss_d, info = discriminator_loss(  # eq. 12
                disc, p.x_prev_real, p.x_prev_fake, p.x_t, p.cond, p.k, config.r1_gamma
            )
            loss_g = torch.full((), float("nan"))
            if torch.isfinite(loss_d):  # alternate: step D, then G against the updated D
                optimizer_step(run.opt_d, loss_d, list(disc.parameters()), config.grad_clip)
                loss_g = generator_loss(disc, p.x_prev_fake, p.x_t, p.cond, p.k)  # eq. 11
            info["loss_g"] = loss_g.item()
            if not (torch.isfinite(loss_d) and torch.isfinite(loss_g)):
                raise _diverged(run.step + 1, loss_d, loss_g, checkpoint, run.last_good)
            optimizer_step(
                run.opt_g, loss_g, list(gan.parameters()), config.grad_clip, only_these=True
            )
            ema_update(run.ema, gan, config.ema_decay, run.step)
            run.step += 1
            record = {"step": run.step, **info, "seconds": time.perf_counter() - t0}
            history.append(record)
            if checkpoint is not None and _checkpoint_due(run.step, config):
                _save_ddgan(checkpoint, bundle, gan, disc, run, metadata, config)
            if callback is not None:
                callback(run.step, {**record, "ema": run.ema})
        gan.load_state_dict(run.ema)
        gan.eval()
        disc.eval()
        return history
