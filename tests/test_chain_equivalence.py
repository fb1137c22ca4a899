"""The one reverse chain reproduces the three loops it replaced, bit for bit.

The reference implementations below are the loops of ``ddpm_sample``, ``ddim_sample`` and
``aamdm_sample`` as they were before :func:`minimdm.diffusion.reverse_chain` (copied here on
purpose: they are the specification). For a fixed generator the new samplers must return
identical tensors, call the hooks with identical arguments and count the same steps.
"""

from __future__ import annotations

import pytest
import torch

from minimdm.aamdm.model import AAMDM, AAMDMConfig, Guide, StepCount, aamdm_sample
from minimdm.amdm.models import DenoiserConfig, MLPDenoiser
from minimdm.diffusion import (
    NoiseSchedule,
    ddim_sample,
    ddim_timesteps,
    ddpm_sample,
    predict_eps_from_x0,
    predict_x0_from_eps,
    q_posterior,
    q_posterior_sample,
)

# ----------------------------------------------------------------------------------------------
# Reference implementations: the old loops


def _old_model_x0_eps(model, schedule, x_t, t, cond, predicts, clip_x0):
    tt = torch.full((x_t.shape[0],), t, device=x_t.device, dtype=torch.long)
    out = model(x_t, tt, cond)
    if predicts == "eps":
        eps = out
        x0 = predict_x0_from_eps(schedule, x_t, t, eps)
    else:
        x0 = out
        eps = None
    if clip_x0 is not None:
        x0 = x0.clamp(-clip_x0, clip_x0)
    if eps is None or clip_x0 is not None:
        eps = predict_eps_from_x0(schedule, x_t, t, x0)
    return x0, eps


def _old_p_sample(model, schedule, x_t, t, cond, generator, predicts, clip_x0):
    x0_hat, _ = _old_model_x0_eps(model, schedule, x_t, t, cond, predicts, clip_x0)
    mean, var = q_posterior(schedule, x0_hat, x_t, t)
    if t == 0:
        return mean, x0_hat
    noise = torch.randn(x_t.shape, generator=generator, device=x_t.device, dtype=x_t.dtype)
    return mean + var.sqrt() * noise, x0_hat


@torch.no_grad()
def old_ddpm(model, schedule, shape, cond, generator, hook, predicts, t_start, x_start, clip_x0):
    t_start = schedule.T - 1 if t_start is None else t_start
    x = x_start if x_start is not None else torch.randn(shape, generator=generator)
    for t in range(t_start, -1, -1):
        x, x0_hat = _old_p_sample(model, schedule, x, t, cond, generator, predicts, clip_x0)
        if hook is not None:
            x = hook(t - 1, x, x0_hat)
    return x


@torch.no_grad()
def old_ddim(model, schedule, shape, cond, steps, eta, generator, hook, predicts, x_start, clip):
    ts = ddim_timesteps(schedule.T, steps or schedule.T)
    x = x_start if x_start is not None else torch.randn(shape, generator=generator)
    ac = schedule.alphas_cumprod
    for i, t in enumerate(ts):
        t_next = ts[i + 1] if i + 1 < len(ts) else -1
        x0_hat, eps = _old_model_x0_eps(model, schedule, x, t, cond, predicts, clip)
        a_t = ac[t]
        a_next = ac[t_next] if t_next >= 0 else torch.ones_like(a_t)
        sigma = eta * ((1 - a_next) / (1 - a_t)).sqrt() * (1 - a_t / a_next).clamp(min=0).sqrt()
        x = a_next.sqrt() * x0_hat + (1 - a_next - sigma**2).clamp(min=0).sqrt() * eps
        if t_next >= 0 and eta > 0:
            x = x + sigma * torch.randn(x.shape, generator=generator, dtype=x.dtype)
        if hook is not None:
            x = hook(t_next, x, x0_hat)
    return x


def _old_with_grad_x0(fn, x_t, guide, alpha):
    with torch.enable_grad():
        x = x_t.detach().requires_grad_(True)
        x0 = fn(x)
        J = guide.cost(x0)
        (grad,) = torch.autograd.grad(J.sum(), x)
    return x0.detach() - guide.scale * alpha * grad


@torch.no_grad()
def old_aamdm(gan, polisher, schedule, shape, cond, T_gan, T_adm, generator, hook, guide,
              x_start, clip_x0, count):  # fmt: skip
    T = schedule.T
    gan_only = T_adm == 0 and T_gan < T
    B, D = shape
    latent = gan.config.latent_dim
    x = x_start if x_start is not None else torch.randn((B, D), generator=generator)
    t_low = T - T_gan
    for t in range(T - 1, -1 if not gan_only else t_low - 1, -1):
        tt = torch.full((B,), t, dtype=torch.long)
        if t >= t_low:
            r = torch.randn((B, latent), generator=generator)

            def fn(x_in, k=tt - t_low, r=r):
                return gan(x_in, k, cond, r)

            module = "gan"
        else:

            def fn(x_in, tt=tt):
                return polisher(x_in, tt, cond)

            module = "adm"
        if guide is not None:
            x0_hat = _old_with_grad_x0(fn, x, guide, schedule.alphas[t])
        else:
            x0_hat = fn(x)
        if clip_x0 is not None:
            x0_hat = x0_hat.clamp(-clip_x0, clip_x0)
        if count is not None:
            count.levels.append(t)
            count.modules.append(module)
        last = t == 0 or (gan_only and t == t_low)
        x = x0_hat if last else q_posterior_sample(schedule, x0_hat, x, t, generator)
        if hook is not None:
            x = hook(-1 if last else t - 1, x, x0_hat)
    return x


# ----------------------------------------------------------------------------------------------
# Fixtures


def denoiser(predicts: str, seed: int = 0) -> MLPDenoiser:
    torch.manual_seed(seed)
    return MLPDenoiser(DenoiserConfig(3, 3, width=16, depth=2, time_dim=8, predicts=predicts))


class Recording:
    """A hook on x_t that records its arguments and shifts the sample (so its output matters)."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, torch.Tensor, torch.Tensor]] = []

    def __call__(self, t, x, x0):
        self.calls.append((t, x.clone(), x0.clone()))
        return x + 0.01 * t


def assert_same_calls(a: Recording, b: Recording) -> None:
    assert [c[0] for c in a.calls] == [c[0] for c in b.calls]
    for (_, xa, x0a), (_, xb, x0b) in zip(a.calls, b.calls, strict=True):
        assert torch.equal(xa, xb) and torch.equal(x0a, x0b)


# ----------------------------------------------------------------------------------------------
# DDPM and DDIM


@pytest.mark.parametrize("predicts", ["eps", "x0"])
@pytest.mark.parametrize("clip_x0", [None, 0.7])
@pytest.mark.parametrize("t_start", [None, 3])
@pytest.mark.parametrize("hooked", [False, True])
def test_ddpm_is_bit_identical_to_the_old_loop(predicts, clip_x0, t_start, hooked):
    model, s = denoiser(predicts), NoiseSchedule("cosine", 8)
    cond = torch.randn(5, 3, generator=torch.Generator().manual_seed(9))
    x_start = None if t_start is None else torch.randn(5, 3)
    h_old, h_new = (Recording(), Recording()) if hooked else (None, None)
    old = old_ddpm(model, s, (5, 3), cond, torch.Generator().manual_seed(1), h_old, predicts,
                   t_start, x_start, clip_x0)  # fmt: skip
    new = ddpm_sample(model, s, (5, 3), cond=cond, generator=torch.Generator().manual_seed(1),
                      hook=h_new, predicts=predicts, t_start=t_start, x_start=x_start,
                      clip_x0=clip_x0)  # fmt: skip
    assert torch.equal(old, new)
    if hooked:
        assert_same_calls(h_old, h_new)


@pytest.mark.parametrize("predicts", ["eps", "x0"])
@pytest.mark.parametrize("clip_x0", [None, 0.7])
@pytest.mark.parametrize("steps,eta", [(None, 0.0), (4, 0.0), (4, 1.0), (3, 0.5)])
@pytest.mark.parametrize("hooked", [False, True])
def test_ddim_is_bit_identical_to_the_old_loop(predicts, clip_x0, steps, eta, hooked):
    model, s = denoiser(predicts, 1), NoiseSchedule("linear", 10)
    cond = torch.randn(4, 3, generator=torch.Generator().manual_seed(8))
    h_old, h_new = (Recording(), Recording()) if hooked else (None, None)
    x_start = torch.randn(4, 3) if hooked else None
    old = old_ddim(model, s, (4, 3), cond, steps, eta, torch.Generator().manual_seed(2), h_old,
                   predicts, x_start, clip_x0)  # fmt: skip
    new = ddim_sample(model, s, (4, 3), cond=cond, steps=steps, eta=eta,
                      generator=torch.Generator().manual_seed(2), hook=h_new, predicts=predicts,
                      x_start=x_start, clip_x0=clip_x0)  # fmt: skip
    assert torch.equal(old, new)
    if hooked:
        assert_same_calls(h_old, h_new)


# ----------------------------------------------------------------------------------------------
# AAMDM


def tiny_aamdm(T_gan=3, T_adm=2) -> AAMDM:
    torch.manual_seed(0)
    return AAMDM(AAMDMConfig(2, 2, T_gan, T_adm, latent_dim=3, width=16, depth=2, time_dim=8))


@pytest.mark.parametrize("T_adm", [2, 0])
@pytest.mark.parametrize("clip_x0", [None, 0.5])
@pytest.mark.parametrize("guided", [False, True])
@pytest.mark.parametrize("hooked", [False, True])
def test_aamdm_is_bit_identical_to_the_old_loop(T_adm, clip_x0, guided, hooked):
    m = tiny_aamdm()
    s = m.schedule()
    cond = torch.randn(6, 2, generator=torch.Generator().manual_seed(4))
    target = torch.tensor([0.3, -0.2])
    guide = Guide(lambda x0: ((x0 - target) ** 2).sum(-1), 0.4) if guided else None
    h_old, h_new = (Recording(), Recording()) if hooked else (None, None)
    x_start = torch.randn(6, 2) if hooked else None
    c_old, c_new = StepCount(), StepCount()
    args = (m.generator, m.polisher, s, (6, 2), cond, 3, T_adm)
    old = old_aamdm(*args, torch.Generator().manual_seed(5), h_old, guide, x_start, clip_x0, c_old)
    new = aamdm_sample(*args, torch.Generator().manual_seed(5), h_new, guide, x_start, clip_x0,
                       c_new)  # fmt: skip
    assert torch.equal(old, new)
    assert (c_old.levels, c_old.modules) == (c_new.levels, c_new.modules)
    if hooked:
        assert_same_calls(h_old, h_new)


def test_aamdm_method_matches_the_old_loop_with_its_own_clamp():
    m = tiny_aamdm()
    m.config.clip_x0 = 0.5
    cond = torch.randn(3, 2)
    count = StepCount()
    new = m.sample(cond, torch.Generator().manual_seed(7), count=count)
    old = old_aamdm(m.generator, m.polisher, m.schedule(), (3, 2), cond, 3, 2,
                    torch.Generator().manual_seed(7), None, None, None, 0.5, None)  # fmt: skip
    assert torch.equal(old, new) and count.network_calls == 5
