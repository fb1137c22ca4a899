"""Diffusion: noise schedules, the forward process, the posterior and the one reverse chain.

Notation follows Ho et al. (2020) and the A-MDM paper (Shi et al. 2024, §3.1):

* ``t`` is a 0-based step index, ``0 <= t < T``. Index ``t`` is the paper's step ``t + 1``:
  ``x_t`` below is the paper's :math:`x^{t+1}`. We extend it by one value, ``t = -1``, which
  denotes clean data (the paper's :math:`x^0`), so that every sample in the reverse chain has a
  level: noise enters at ``T - 1`` and the last step leaves at ``-1``.
* Every function is batched over the leading dimension, works on any device, and draws its
  randomness from an explicit :class:`torch.Generator`. The chain draws it through
  :func:`gaussian`, which also takes a :class:`NoiseTape`: the noise drawn in advance, so that a
  frame's whole chain can take its noise as an input (the fast path, :mod:`minimdm.fast`).

**The reverse chain.** :func:`reverse_chain` is the library's only loop over denoising levels.
At each level a *step rule* (:class:`StepRule`) asks its network for the clean estimate
:math:`\\hat x_0` and draws the sample at the next level from it. The rule changes, the loop
does not:

* :class:`DDPMStep`: the ancestral step of Ho et al. Algorithm 2, one level at a time;
* :class:`DDIMStep`: Song et al. (2021) eq. 12 with stochasticity ``eta``, over any decreasing
  subsequence of levels (:func:`ddim_timesteps`, which may start at ``t_start``);
* :class:`DDGANStep`: the DD-GAN generation step (Xiao et al. 2022; AAMDM §3.3): a generator
  with a latent ``r`` predicts :math:`\\hat x_0`, then the posterior is sampled;
* :class:`PolishStep`: the AAMDM polishing step (§3.2): an x0-predicting polisher, then the
  Gaussian posterior step;
* :class:`Handover` joins two rules in one chain (AAMDM's GAN levels, then polishing levels).

Denoisers are callables ``model(x_t, t, cond) -> prediction`` with ``x_t`` of shape ``(B, D)``,
``t`` a ``(B,)`` long tensor and ``cond`` a ``(B, C)`` context tensor (or ``None``); the
prediction is the noise ``eps`` (A-MDM eq. 3), the clean sample ``x0`` or the velocity ``v``
(Salimans & Ho 2022), as named by ``predicts``.

**Hooks.** The chain calls two kinds of hooks, so that control never copies the loop:

* *hooks on* :math:`\\hat x_0`, ``hook(t, x_t, x0_hat) -> x0_hat``, change the network's clean
  estimate before the step uses it: the guidance of AAMDM eq. 13 (a hook with
  ``needs_grad = True`` gets an ``x_t`` it can differentiate through the network) and the clamp
  to the training data's per-feature range (:func:`clip_bounds`, :func:`data_range`);
* *hooks on* :math:`x_t`, ``hook(t, x_t, x0_hat) -> x_t``, run after each step, where ``x_t`` is
  the new sample at level ``t`` (``t = -1``: the final clean sample) and ``x0_hat`` the estimate
  that step used: inpainting (A-MDM eq. 4, :mod:`minimdm.control.hooks`); the RL residuals
  of A-MDM eq. 7 take the same form.

:func:`ddpm_sample`, :func:`ddim_sample`, :func:`p_sample` and
:func:`minimdm.aamdm.model.aamdm_sample` are thin calls of the chain.

The package's modules: :mod:`~minimdm.diffusion.schedule` (schedules, the forward process, the
posterior, the loss), :mod:`~minimdm.diffusion.clamp` (the clamp of the clean estimate),
:mod:`~minimdm.diffusion.chain` (step rules and the loop) and
:mod:`~minimdm.diffusion.samplers` (DDPM and DDIM on the chain).
"""

from .chain import (
    DDGANStep,
    DDIMStep,
    DDPMStep,
    Handover,
    PolishStep,
    StepCount,
    StepRule,
    chain_step,
    predict_x0,
    reverse_chain,
)
from .clamp import clamp_hook, clamp_share, clamp_x0, clip_bounds, data_range
from .samplers import (
    StepSettings,
    ddim_sample,
    ddim_timesteps,
    ddpm_sample,
    hook_list,
    p_mean_variance,
    p_sample,
    start_chain,
)
from .schedule import (
    PREDICTS,
    ClipX0,
    Denoiser,
    Hook,
    NoiseSchedule,
    NoiseTape,
    X0Hook,
    check_finite,
    diffusion_loss,
    gaussian,
    predict_eps_from_v,
    predict_eps_from_x0,
    predict_v,
    predict_x0_from_eps,
    predict_x0_from_v,
    q_posterior,
    q_posterior_sample,
    q_sample,
)

__all__ = [
    "Hook",
    "X0Hook",
    "Denoiser",
    "ClipX0",
    "NoiseSchedule",
    "NoiseTape",
    "gaussian",
    "q_sample",
    "q_posterior",
    "q_posterior_sample",
    "predict_x0_from_eps",
    "predict_eps_from_x0",
    "predict_v",
    "predict_x0_from_v",
    "predict_eps_from_v",
    "PREDICTS",
    "clip_bounds",
    "clamp_x0",
    "clamp_hook",
    "data_range",
    "clamp_share",
    "StepRule",
    "DDPMStep",
    "DDIMStep",
    "DDGANStep",
    "PolishStep",
    "Handover",
    "StepCount",
    "predict_x0",
    "chain_step",
    "reverse_chain",
    "p_mean_variance",
    "p_sample",
    "StepSettings",
    "hook_list",
    "start_chain",
    "ddpm_sample",
    "ddim_sample",
    "ddim_timesteps",
    "diffusion_loss",
    "check_finite",
]
