"""Tests for minimdm.diffusion: schedules, forward process, posterior, the reverse chain with its
step rules and hooks, the x0 clamp, errors.

The closed forms are re-derived here independently of the library (Bayes' rule for the
posterior, a Gaussian data distribution whose optimal denoiser is known in closed form), so
that the tests check the maths and not the code against itself.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from minimdm.amdm.models import DenoiserConfig, MLPDenoiser, skip_weights
from minimdm.diffusion import (
    DDGANStep,
    DDIMStep,
    DDPMStep,
    Handover,
    NoiseSchedule,
    PolishStep,
    StepCount,
    clamp_share,
    clamp_x0,
    clip_bounds,
    data_range,
    ddim_sample,
    ddim_timesteps,
    ddpm_sample,
    diffusion_loss,
    p_mean_variance,
    p_sample,
    predict_eps_from_x0,
    predict_x0_from_eps,
    q_posterior,
    q_sample,
    reverse_chain,
)
from minimdm.toy.squ9 import Squ9, squ9_metrics, train_denoiser

KINDS = ["linear", "cosine", "karras"]
TS = [1, 2, 5, 40, 1000]


def tiny_model(seed: int = 0, x_dim: int = 2, cond_dim: int = 2) -> MLPDenoiser:
    torch.manual_seed(seed)
    return MLPDenoiser(DenoiserConfig(x_dim, cond_dim, width=16, depth=2, time_dim=8)).eval()


def gaussian_eps_model(schedule: NoiseSchedule, mu: float, s: float):
    """The optimal noise predictor E[eps | x_t] when the data is N(mu, s^2) in every coordinate.

    x_t = a x0 + b eps with a = sqrt(abar), b = sqrt(1 - abar), so (x_t, eps) are jointly Gaussian
    and E[eps | x_t] = b (x_t - a mu) / (a^2 s^2 + b^2).
    """

    def model(x_t, t, cond):
        abar = schedule.alphas_cumprod.double()[t].to(x_t.dtype)[:, None]  # (B, 1)
        a, b = abar.sqrt(), (1 - abar).sqrt()
        return b * (x_t - a * mu) / (a**2 * s**2 + b**2)

    return model


# ----------------------------------------------------------------------------------------------
# Schedules


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("T", TS)
def test_schedule_properties(kind, T):
    s = NoiseSchedule(kind, T)
    assert s.T == T
    for name in ("betas", "alphas_cumprod", "posterior_variance", "posterior_mean_coef1"):
        buf = getattr(s, name)
        assert buf.shape == (T,) and buf.dtype == torch.float32, name
    assert ((s.betas > 0) & (s.betas < 1)).all()
    ac = s.alphas_cumprod
    assert ((ac > 0) & (ac < 1)).all()
    assert (ac[1:] < ac[:-1]).all(), "alphas_cumprod must be strictly decreasing"
    # \bar\alpha_t is the running product of 1 - \beta_t (checked with a plain loop, float64)
    prod, ref = 1.0, []
    for b in s.betas.double().tolist():
        prod *= 1 - b
        ref.append(prod)
    torch.testing.assert_close(
        ac.double(), torch.tensor(ref, dtype=torch.float64), rtol=2e-4, atol=0
    )
    # the last level is close to pure noise for every T (the sampler starts from N(0, I))
    assert ac[-1] < 0.02


def test_karras_levels_run_from_the_clean_end_to_pure_noise():
    """Karras et al. 2022 eq. 5 as VP levels: the noise-to-signal ratios run from
    KARRAS_SIGMAS[0] to [1], crowded at the clean end (rho = 7), where the cosine schedule of
    the same T starts 9 times noisier."""
    from minimdm.diffusion.schedule import KARRAS_RHO, KARRAS_SIGMAS

    ac = NoiseSchedule("karras", 20).alphas_cumprod.double()
    sigma = ((1 - ac) / ac).sqrt()
    ends = torch.tensor(KARRAS_SIGMAS, dtype=torch.float64)
    torch.testing.assert_close(sigma[[0, -1]], ends, rtol=1e-3, atol=0)  # stored as float32
    root = sigma ** (1 / KARRAS_RHO)  # evenly spaced in sigma^(1/rho)
    torch.testing.assert_close(root.diff(), root.diff().mean().expand(19), rtol=1e-3, atol=0)
    cosine = NoiseSchedule("cosine", 20).alphas_cumprod.double()
    assert ((1 - cosine[0]) / cosine[0]).sqrt() > 8 * sigma[0]
    with pytest.raises(ValueError, match="'karras'"):
        NoiseSchedule("sigmoid", 20)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("T", TS)
def test_posterior_variance_closed_form(kind, T):
    """\\tilde\\beta_t from Bayes: 1/var = \\alpha_t/\\beta_t + 1/(1-\\bar\\alpha_{t-1})."""
    s = NoiseSchedule(kind, T)
    b = s.betas.double()
    ac = torch.cumprod(1 - b, 0)
    ac_prev = torch.cat([torch.ones(1, dtype=torch.float64), ac[:-1]])
    precision = (1 - b) / b + 1 / (1 - ac_prev)  # inf at t = 0: the posterior is a point mass
    expected = 1 / precision
    torch.testing.assert_close(s.posterior_variance.double(), expected, rtol=1e-4, atol=1e-12)
    assert s.posterior_variance[0] == 0
    # and q_posterior returns it, broadcast to the sample's shape
    x = torch.randn(3, 4)
    _, var = q_posterior(s, x, x, T - 1)
    assert var.shape == (3, 4)
    torch.testing.assert_close(var[0, 0].double(), expected[-1], rtol=1e-4, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("T", [2, 5, 40])
def test_q_posterior_mean_bayes(kind, T):
    """Bayes: mu = var (sqrt(alpha_t) x_t / beta_t + sqrt(abar_{t-1}) x_0 / (1 - abar_{t-1}))."""
    s = NoiseSchedule(kind, T)
    g = torch.Generator().manual_seed(0)
    x0, x_t = (
        torch.randn(5, 3, generator=g, dtype=torch.float64),
        torch.randn(5, 3, generator=g, dtype=torch.float64),
    )
    b = s.betas.double()
    ac = torch.cumprod(1 - b, 0)
    for t in range(1, T):
        var = 1 / ((1 - b[t]) / b[t] + 1 / (1 - ac[t - 1]))
        expected = var * ((1 - b[t]).sqrt() * x_t / b[t] + ac[t - 1].sqrt() * x0 / (1 - ac[t - 1]))
        mean, _ = q_posterior(s, x0, x_t, t)
        torch.testing.assert_close(mean, expected, rtol=1e-4, atol=1e-5)
    # at t = 0 the posterior collapses onto x0
    mean, var = q_posterior(s, x0, x_t, 0)
    torch.testing.assert_close(mean, x0, rtol=1e-5, atol=1e-6)
    assert (var == 0).all()


@pytest.mark.parametrize("kind", KINDS)
def test_q_sample_statistics(kind):
    """x_t ~ N(sqrt(abar) x0, (1 - abar) I): check mean and variance within 5 standard errors."""
    s = NoiseSchedule(kind, 40)
    n = 100_000
    x0 = torch.full((n, 2), 1.5)
    g = torch.Generator().manual_seed(1)
    for t in (0, 10, 39):
        ac = s.alphas_cumprod[t].double()
        x_t = q_sample(s, x0, t, generator=g).double()
        var = 1 - ac
        se_mean = (var / n).sqrt()
        se_var = var * math.sqrt(2 / (n - 1))
        assert (x_t.mean(0) - ac.sqrt() * 1.5).abs().max() < 5 * se_mean
        assert (x_t.var(0) - var).abs().max() < 5 * se_var
    # per-sample steps, and t = -1 leaves the data clean
    t = torch.tensor([-1, 0, 39])
    x_t = q_sample(s, x0[:3], t, noise=torch.zeros(3, 2))
    torch.testing.assert_close(
        x_t[:, 0], 1.5 * torch.tensor([1.0, *s.sqrt_alphas_cumprod[[0, 39]]])
    )


@settings(max_examples=60, deadline=None)
@given(
    kind=st.sampled_from(KINDS),
    T=st.sampled_from(TS),
    frac=st.floats(0, 1),
    seed=st.integers(0, 2**31 - 1),
    scale=st.floats(1e-3, 1e3),
)
def test_eps_x0_round_trip(kind, T, frac, seed, scale):
    s = NoiseSchedule(kind, T)
    t = min(int(frac * T), T - 1)
    g = torch.Generator().manual_seed(seed)
    x0 = scale * torch.randn(4, 3, generator=g, dtype=torch.float64)
    eps = torch.randn(4, 3, generator=g, dtype=torch.float64)
    x_t = q_sample(s, x0, t, noise=eps)
    # conversions invert each other (float64: exact up to rounding)
    eps_rt = predict_eps_from_x0(s, x_t, t, predict_x0_from_eps(s, x_t, t, eps))
    torch.testing.assert_close(eps_rt, eps, rtol=1e-6, atol=1e-6 * (1 + scale))
    x0_rt = predict_x0_from_eps(s, x_t, t, predict_eps_from_x0(s, x_t, t, x0))
    torch.testing.assert_close(x0_rt, x0, rtol=1e-6, atol=1e-6 * (1 + scale))
    # and they invert q_sample; the buffers are float32, so the error grows with 1/sqrt(abar)
    tol = 1e-6 * float(s.sqrt_recip_alphas_cumprod[t]) * (1 + scale)
    torch.testing.assert_close(predict_x0_from_eps(s, x_t, t, eps), x0, rtol=1e-5, atol=tol)
    # eps from x0 cancels the data term: the error grows with scale / sqrt(1/abar - 1)
    tol = 1e-6 * (1 + scale) * (1 + 1 / float(s.sqrt_recipm1_alphas_cumprod[t]))
    torch.testing.assert_close(predict_eps_from_x0(s, x_t, t, x0), eps, rtol=1e-5, atol=tol)


# ----------------------------------------------------------------------------------------------
# Samplers


@pytest.mark.parametrize("sampler", ["ddpm", "ddim"])
def test_sampler_shape_device_seed(sampler):
    s = NoiseSchedule("cosine", 10)
    model = tiny_model()
    cond = torch.randn(6, 2, generator=torch.Generator().manual_seed(0))

    def run(seed):
        g = torch.Generator().manual_seed(seed)
        if sampler == "ddpm":
            return ddpm_sample(model, s, (6, 2), cond=cond, generator=g)
        return ddim_sample(model, s, (6, 2), cond=cond, steps=4, eta=1.0, generator=g)

    a, b, c = run(0), run(0), run(1)
    assert a.shape == (6, 2) and a.dtype == torch.float32 and a.device.type == "cpu"
    assert torch.isfinite(a).all()
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.allclose(a, c)


def test_ddim_eta0_deterministic_given_start():
    s = NoiseSchedule("cosine", 10)
    model = tiny_model()
    cond = torch.randn(6, 2)
    x_T = torch.randn(6, 2)
    a = ddim_sample(
        model,
        s,
        (6, 2),
        cond=cond,
        steps=5,
        x_start=x_T,
        generator=torch.Generator().manual_seed(0),
    )
    b = ddim_sample(
        model,
        s,
        (6, 2),
        cond=cond,
        steps=5,
        x_start=x_T,
        generator=torch.Generator().manual_seed(9),
    )
    torch.testing.assert_close(a, b, rtol=0, atol=0)


def exact_sampler_std(schedule: NoiseSchedule, mu: float, s: float, ts: list[int], ddim: bool):
    """Std of the samples when the data is N(mu, s^2) and the denoiser is exact.

    Every step is then affine in x, x_{next} = A x + c (+ noise), so the variance follows
    v <- A^2 v + noise variance, starting from v = 1. The coefficients are re-derived here:
    DDPM from Bayes' rule for q(x_{t-1} | x_t, x_0), DDIM (eta = 0) from Song et al. eq. 12.
    """
    ac = torch.cumprod(1 - schedule.betas.double(), 0)
    v = torch.tensor(1.0, dtype=torch.float64)
    for i, t in enumerate(ts):
        a, b = ac[t].sqrt(), (1 - ac[t]).sqrt()
        k_eps = b / (a**2 * s**2 + b**2)  # d eps_hat / dx
        k_x0 = (1 - b * k_eps) / a  # d x0_hat / dx
        if ddim:
            t_next = ts[i + 1] if i + 1 < len(ts) else -1
            a_next = ac[t_next] if t_next >= 0 else torch.tensor(1.0, dtype=torch.float64)
            v = (a_next.sqrt() * k_x0 + (1 - a_next).sqrt() * k_eps) ** 2 * v
        else:
            beta, a_prev = 1 - ac[t] / (ac[t - 1] if t else 1), ac[t - 1] if t else 1
            var = 1 / ((1 - beta) / beta + 1 / (1 - a_prev)) if t else torch.tensor(0.0)
            A = (
                var * ((1 - beta).sqrt() / beta + (a_prev**0.5) * k_x0 / (1 - a_prev))
                if t
                else k_x0
            )
            v = A**2 * v + var
    return v.sqrt().item()


@pytest.mark.parametrize("sampler,steps", [("ddpm", 250), ("ddim", 250), ("ddim", 25)])
def test_samplers_on_gaussian_data(sampler, steps):
    """With the exact denoiser of N(mu, s^2) data, the samples have the predicted mean and std.

    The spread is a little below s = 0.3 (DDPM with the posterior variance: 0.293; DDIM with 250
    steps: 0.297, with 25 steps: 0.274) and converges to s as the steps grow; the test checks
    the exact value for these steps.
    """
    mu, sd = 0.7, 0.3
    s = NoiseSchedule("cosine", 250)
    model = gaussian_eps_model(s, mu, sd)
    g = torch.Generator().manual_seed(3)
    shape = (2000, 8)  # 16k values: small enough for single-threaded elementwise ops
    if sampler == "ddpm":
        x = ddpm_sample(model, s, shape, generator=g, dtype=torch.float64)
        std = exact_sampler_std(s, mu, sd, list(range(249, -1, -1)), ddim=False)
    else:
        x = ddim_sample(model, s, shape, steps=steps, generator=g, dtype=torch.float64)
        std = exact_sampler_std(s, mu, sd, ddim_timesteps(250, steps), ddim=True)
    n = x.numel()
    assert abs(std / sd - 1) < (0.1 if steps < 250 else 0.03)
    assert abs(x.mean().item() - mu) < 5 * std / math.sqrt(n)
    assert abs(x.std().item() - std) < 5 * std / math.sqrt(2 * n)


def test_hook_order_ddpm():
    T = 7
    s = NoiseSchedule("linear", T)
    seen = []

    def hook(t, x_t, x0_hat):
        assert x_t.shape == x0_hat.shape == (3, 2)
        seen.append(t)
        return x_t

    ddpm_sample(tiny_model(), s, (3, 2), cond=torch.zeros(3, 2), hook=hook)
    assert seen == list(range(T - 2, -2, -1))  # T-2, ..., 0, -1: once per step


@pytest.mark.parametrize("steps", [1, 3, 10])
def test_hook_order_ddim(steps):
    T = 10
    s = NoiseSchedule("cosine", T)
    seen = []
    ddim_sample(
        tiny_model(),
        s,
        (3, 2),
        cond=torch.zeros(3, 2),
        steps=steps,
        hook=lambda t, x, x0: seen.append(t) or x,
    )
    ts = ddim_timesteps(T, steps)
    assert ts[0] == T - 1 and len(ts) == steps
    assert all(a > b for a, b in zip(ts, ts[1:], strict=False))
    assert seen == ts[1:] + [-1]


def test_hook_output_is_used():
    """Whatever the hook returns is the chain's next state: zeroing at the end gives zeros."""
    s = NoiseSchedule("cosine", 5)
    hook = lambda t, x, x0: torch.zeros_like(x) if t == -1 else x  # noqa: E731
    for out in (
        ddpm_sample(tiny_model(), s, (4, 2), cond=torch.ones(4, 2), hook=hook),
        ddim_sample(tiny_model(), s, (4, 2), cond=torch.ones(4, 2), hook=hook),
    ):
        assert (out == 0).all()


def test_partial_chain_t_start_x_start():
    T = 8
    s = NoiseSchedule("cosine", T)
    model = tiny_model()
    cond = torch.randn(5, 2)
    # a full chain equals starting at T-1 from the same noise
    g = torch.Generator().manual_seed(4)
    full = ddpm_sample(model, s, (5, 2), cond=cond, generator=g)
    g = torch.Generator().manual_seed(4)
    x_T = torch.randn(5, 2, generator=g)
    torch.testing.assert_close(
        ddpm_sample(model, s, (5, 2), cond=cond, generator=g, x_start=x_T), full
    )
    # a chain from level 3 runs exactly 4 steps: the same as calling p_sample by hand
    x3 = torch.randn(5, 2)
    seen = []
    g = torch.Generator().manual_seed(5)
    out = ddpm_sample(
        model,
        s,
        (5, 2),
        cond=cond,
        generator=g,
        t_start=3,
        x_start=x3,
        hook=lambda t, x, x0: seen.append(t) or x,
    )
    assert seen == [2, 1, 0, -1]
    g = torch.Generator().manual_seed(5)
    x = x3
    for t in (3, 2, 1, 0):
        x, _ = p_sample(model, s, x, t, cond, generator=g)
    torch.testing.assert_close(out, x)


def test_diffusion_loss_oracle():
    """An oracle that knows the (constant) data reaches zero loss in both parameterisations."""
    s = NoiseSchedule("cosine", 20)
    c = torch.tensor([[0.5, -1.0]]).expand(64, 2)

    def eps_oracle(x_t, t, cond):
        return predict_eps_from_x0(s, x_t, t, c)

    def x0_oracle(x_t, t, cond):
        return c.clone()

    g = torch.Generator().manual_seed(0)
    loss, x0_hat = diffusion_loss(eps_oracle, s, c, generator=g)
    assert loss.item() < 1e-8
    torch.testing.assert_close(x0_hat, c, rtol=1e-4, atol=1e-4)
    loss, _ = diffusion_loss(x0_oracle, s, c, generator=g, predicts="x0")
    assert loss.item() == 0
    # a model that outputs zeros has loss E|eps|^2 = 1
    loss, _ = diffusion_loss(lambda x, t, cc: torch.zeros_like(x), s, c.repeat(100, 1), generator=g)
    assert abs(loss.item() - 1) < 0.1
    per_sample, _ = diffusion_loss(eps_oracle, s, c, generator=g, reduce=False)
    assert per_sample.shape == (64,)


# ----------------------------------------------------------------------------------------------
# Bad input


def test_bad_input_raises():
    with pytest.raises(ValueError, match="T must"):
        NoiseSchedule("linear", 0)
    with pytest.raises(ValueError, match="kind"):
        NoiseSchedule("quadratic", 10)
    for betas in ([0.1, 1.0], [0.0, 0.5], [-0.1], [0.2, float("nan")]):
        with pytest.raises(ValueError, match="betas"):
            NoiseSchedule(betas=torch.tensor(betas))
    s = NoiseSchedule("cosine", 5)
    model = tiny_model()
    with pytest.raises(ValueError, match="cond"):  # wrong batch size
        ddpm_sample(model, s, (4, 2), cond=torch.zeros(3, 2))
    with pytest.raises(ValueError, match="cond"):  # wrong feature size
        ddpm_sample(model, s, (4, 2), cond=torch.zeros(4, 3), cond_dim=2)
    with pytest.raises(ValueError, match="cond"):  # wrong feature size, caught by the model
        ddim_sample(model, s, (4, 2), cond=torch.zeros(4, 3))
    nan_cond = torch.zeros(4, 2)
    nan_cond[2, 1] = float("nan")
    for sampler in (ddpm_sample, ddim_sample):
        with pytest.raises(ValueError, match="cond"):
            sampler(model, s, (4, 2), cond=nan_cond)
        with pytest.raises(ValueError, match="x_start"):
            sampler(model, s, (4, 2), cond=torch.zeros(4, 2), x_start=torch.zeros(4, 3))
    with pytest.raises(ValueError, match="t_start"):
        ddpm_sample(model, s, (4, 2), cond=torch.zeros(4, 2), t_start=5)
    with pytest.raises(ValueError, match="steps"):
        ddim_sample(model, s, (4, 2), cond=torch.zeros(4, 2), steps=6)
    with pytest.raises(ValueError, match="eta"):
        ddim_sample(model, s, (4, 2), cond=torch.zeros(4, 2), eta=-1)
    with pytest.raises(ValueError, match="t must"):
        q_sample(s, torch.zeros(4, 2), 5)


# ----------------------------------------------------------------------------------------------
# The reverse chain: step rules and the two kinds of hooks


class ConstNet(torch.nn.Module):
    """Predicts a constant clean sample c and records the levels it is called at."""

    def __init__(self, c: float = 0.3):
        super().__init__()
        self.c, self.levels = c, []

    def forward(self, x_t, t, cond):
        self.levels.append(int(t[0]))
        return torch.full_like(x_t, self.c)


def test_chain_runs_each_level_once_and_rejects_bad_levels():
    s = NoiseSchedule("cosine", 10)
    net = ConstNet()
    x = torch.randn(3, 2)
    out = reverse_chain(DDIMStep(net, s, "x0", eta=0.0), x, [9, 5, 2])
    assert net.levels == [9, 5, 2]
    # eta = 0 and a constant x0 estimate: the last step lands exactly on it
    assert torch.equal(out, torch.full((3, 2), 0.3))
    for bad in ([], [3, 5], [4, 4], [2, -1]):
        with pytest.raises(ValueError, match="levels"):
            reverse_chain(DDIMStep(net, s, "x0"), x, bad)
    with pytest.raises(ValueError, match="DDPM step goes one level down"):
        reverse_chain(DDPMStep(net, s, "x0"), x, [5, 2])


def test_x0_hooks_run_before_the_step_and_x_t_hooks_after():
    s = NoiseSchedule("linear", 6)
    events = []

    def x0_hook(t, x_t, x0_hat):
        events.append(("x0", t))
        return torch.full_like(x0_hat, -1.0)  # the step must use this estimate

    def x_hook(t, x_t, x0_hat):
        events.append(("x", t))
        assert (x0_hat == -1.0).all()  # x_t hooks see the estimate the step used
        return x_t

    out = reverse_chain(
        DDIMStep(tiny_model(), s, "eps", eta=0.0), torch.randn(4, 2), [5, 3, 0],
        torch.zeros(4, 2), hooks=[x_hook], x0_hooks=[x0_hook],
    )  # fmt: skip
    assert events == [("x0", 5), ("x", 3), ("x0", 3), ("x", 0), ("x0", 0), ("x", -1)]
    torch.testing.assert_close(out, torch.full((4, 2), -1.0))


def test_x0_hook_with_needs_grad_can_differentiate_through_the_network():
    """A guidance-like hook gets an x_t that requires grad; d x0_hat / d x_t is the network's."""
    s = NoiseSchedule("cosine", 4)
    net = tiny_model()
    grads = []

    def hook(t, x_t, x0_hat):
        assert x_t.requires_grad
        (g,) = torch.autograd.grad(x0_hat.sum(), x_t)
        grads.append(g)
        return x0_hat.detach()

    hook.needs_grad = True
    x, cond = torch.randn(3, 2), torch.zeros(3, 2)
    reverse_chain(DDPMStep(net, s, "eps"), x, [3, 2, 1, 0], cond, x0_hooks=[hook])
    assert len(grads) == 4 and all(torch.isfinite(g).all() for g in grads)
    # at the first level the gradient is the network's own (computed here independently)
    xg = x.clone().requires_grad_(True)
    x0 = predict_x0_from_eps(s, xg, 3, net(xg, torch.full((3,), 3), cond))
    (ref,) = torch.autograd.grad(x0.sum(), xg)
    torch.testing.assert_close(grads[0], ref)


def test_chain_counts_its_steps_by_rule():
    s = NoiseSchedule("cosine", 6)
    count = StepCount()
    x = torch.randn(2, 2)
    polish = PolishStep(ConstNet(0.1), s)
    gan = DDGANStep(lambda x_t, k, cond, r: x_t * 0 + r[:, :2], s, latent_dim=2, t_offset=2)
    out = reverse_chain(Handover(gan, polish, 2), x, range(5, -1, -1), count=count)
    assert count.levels == [5, 4, 3, 2, 1, 0]
    assert count.modules == ["gan"] * 4 + ["adm"] * 2
    assert (count.gan_steps, count.adm_steps, count.network_calls) == (4, 2, 6)
    assert torch.equal(out, torch.full((2, 2), 0.1))  # the last polishing step returns x0_hat


@pytest.mark.parametrize("steps,t_start", [(5, 12), (5, 19), (20, 7), (3, 0)])
def test_ddim_t_start_follows_the_grid_below_it(steps, t_start):
    T = 20
    ts = ddim_timesteps(T, steps, t_start)
    grid = ddim_timesteps(T, steps)
    assert ts[0] == t_start and ts[1:] == [t for t in grid if t < t_start]
    net = ConstNet()
    seen = []
    x_start = torch.randn(2, 2)
    s = NoiseSchedule("cosine", T)
    out = ddim_sample(net, s, (2, 2), steps=steps, predicts="x0", t_start=t_start,
                      x_start=x_start, hook=lambda t, x, x0: seen.append(t) or x)  # fmt: skip
    assert net.levels == ts and seen == ts[1:] + [-1]
    assert torch.equal(out, torch.full((2, 2), 0.3))
    # starting at T - 1 is the plain chain
    g1, g2 = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    a = ddim_sample(
        tiny_model(),
        s,
        (2, 2),
        cond=torch.zeros(2, 2),
        steps=steps,
        eta=1.0,
        generator=g1,
        t_start=T - 1,
    )
    b = ddim_sample(
        tiny_model(), s, (2, 2), cond=torch.zeros(2, 2), steps=steps, eta=1.0, generator=g2
    )
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="t_start"):
        ddim_sample(net, s, (2, 2), steps=steps, t_start=T)


def test_sampler_frame_passes_t_start_to_ddim():
    from minimdm.amdm.sampling import Sampler
    from minimdm.diffusion import StepSettings

    torch.manual_seed(0)
    model = MLPDenoiser(DenoiserConfig(2, 2, width=16, depth=2, time_dim=8, predicts="x0"))
    levels = []
    model.register_forward_pre_hook(lambda m, args: levels.append(int(args[1][0])))
    s = NoiseSchedule("cosine", 20)
    sampler = Sampler(model, schedule=s, settings=StepSettings(5, 0.0, "x0"))
    sampler.frame(torch.zeros(3, 2), None, t_start=9, x_start=torch.randn(3, 2))
    assert levels == ddim_timesteps(20, 5, 9) and levels[0] == 9


# ----------------------------------------------------------------------------------------------
# The x0 clamp: None, a float, or a per-feature range


finite = st.floats(-50, 50, allow_nan=False)  # float64: data_range must round outwards


@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 5).flatmap(
        lambda d: st.lists(st.lists(finite, min_size=d, max_size=d), min_size=1, max_size=30)
    ),
    st.sampled_from([torch.float32, torch.float64]),
)
def test_data_range_covers_its_frames(rows, dtype):
    frames = torch.tensor(rows, dtype=dtype)
    lo, hi = data_range(frames)
    assert lo.dtype == hi.dtype == torch.float32 and (lo <= hi).all()
    assert clamp_share((lo, hi), frames) == 0.0
    assert torch.equal(clamp_x0(frames.float(), clip_bounds((lo, hi), frames.shape[1])),
                       frames.float())  # fmt: skip
    # a box that excludes one extreme value excludes its frame
    if (hi > lo).any():
        j = int((hi > lo).nonzero()[0])
        hi2 = hi.clone()
        hi2[j] = torch.nextafter(hi[j], torch.tensor(-math.inf))
        n_out = (frames[:, j].double() > hi2[j].double()).sum().item()
        assert n_out >= 1 and clamp_share((lo, hi2), frames) >= n_out / len(frames)


@settings(max_examples=40, deadline=None)
@given(st.lists(finite, min_size=6, max_size=6), st.floats(0.1, 10))
def test_clamp_forms_agree_and_bound_the_estimate(vals, c):
    x = torch.tensor(vals).reshape(2, 3)
    sym = clamp_x0(x, clip_bounds(c, 3))
    pair = clamp_x0(x, clip_bounds([[-c] * 3, [c] * 3], 3))
    assert torch.equal(sym, pair) and (sym.abs() <= torch.tensor(c, dtype=torch.float32)).all()
    assert torch.equal(clamp_x0(sym, clip_bounds(c, 3)), sym)  # idempotent
    assert clip_bounds(None, 3) is None and torch.equal(clamp_x0(x, None), x)


def test_clamp_share_counts_frames_with_any_feature_outside():
    frames = torch.tensor([[0.0, 0.0], [0.0, 6.0], [-7.0, 0.0], [4.9, -4.9]])
    assert clamp_share(5.0, frames) == 0.5
    assert clamp_share([[-8.0, -1.0], [1.0, 7.0]], frames) == 0.25  # [4.9, -4.9] only
    assert clamp_share(None, frames) == 0.0


def test_samplers_take_the_checkpoint_form_of_the_range():
    """Nested lists (the JSON of a checkpoint) clamp per feature in every sampler."""
    s = NoiseSchedule("cosine", 5)
    net = ConstNet(3.0)
    bounds = [[-1.0, -2.0], [0.5, 2.5]]
    for out in (
        ddpm_sample(net, s, (4, 2), predicts="x0", clip_x0=bounds),
        ddim_sample(net, s, (4, 2), steps=3, predicts="x0", clip_x0=bounds),
    ):
        torch.testing.assert_close(out, torch.tensor([[0.5, 2.5]] * 4))
    _, _, x0 = p_mean_variance(net, s, torch.zeros(4, 2), 2, None, "x0", bounds)
    assert x0.tolist() == [[0.5, 2.5]] * 4


@pytest.mark.parametrize(
    "bad,match",
    [
        ([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], r"clip_x0 must be a pair \(lo, hi\) of 2 values"),
        ([[0.0], [1.0]], r"clip_x0 must be a pair \(lo, hi\) of 2 values"),
        ([[0.0, 2.0], [1.0, 1.0]], r"clip_x0 must have lo <= hi, but feature 1"),
        ([[0.0, float("nan")], [1.0, 1.0]], "clip_x0 must hold finite bounds"),
        ([[0.0, 0.0], [1.0, float("inf")]], "clip_x0 must hold finite bounds"),
        ([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]], "clip_x0 must be None, a float"),
        (-1.0, "clip_x0 must be a finite float > 0"),
        (float("nan"), "clip_x0 must be a finite float > 0"),
        ("data", "clip_x0 must be None.*'data' is resolved by training"),
    ],
)
def test_bad_clamp_raises_naming_clip_x0(bad, match):
    s = NoiseSchedule("cosine", 5)
    with pytest.raises(ValueError, match=match):
        clip_bounds(bad, 2)
    for sampler in (ddpm_sample, ddim_sample):
        with pytest.raises(ValueError, match="clip_x0"):
            sampler(tiny_model(), s, (3, 2), cond=torch.zeros(3, 2), clip_x0=bad)


# ----------------------------------------------------------------------------------------------
# End to end: a conditional DDPM learns the many-to-many Squ-9 transitions

# How the bound was measured: this exact configuration (T=20 cosine, MLP 64x4, 1500 steps of
# batch 1024, lr 5e-3, 20k training pairs, 4000 evaluation pairs) was trained with seeds 0-9 on
# the 2-core build machine. Coverage was 1.0 for every seed; precision ranged 0.797-0.851
# (mean 0.82, sd 0.02; seed 0, the one tested: 0.806). The bound 0.7 sits 5 sd below the worst
# seed, so other CPUs (different rounding, hence different training) pass, while blurred
# samplers fail it (chapter 1: T=2 and T=5 score 0.22 and 0.42). Coverage 1.0 rules out
# collapse (the MSE regressor covers 1/9); the ground truth's precision is 1 - exp(-9/2) = 0.989.
E2E_PRECISION_BOUND = 0.7


@pytest.mark.usefixtures("one_thread")  # a tiny model: one thread is as fast, immune to busy cores
def test_e2e_squ9_ddpm_full_coverage():
    _e2e_squ9()


def _e2e_squ9():
    torch.manual_seed(0)
    sq = Squ9()
    g = torch.Generator().manual_seed(0)
    x_prev, x_next = sq.sample_pairs(20_000, g)
    model = MLPDenoiser(DenoiserConfig(2, 2, width=64, depth=4, time_dim=32))
    s = NoiseSchedule("cosine", 20)
    losses = train_denoiser(
        model, s, x_prev, x_next, steps=1500, batch_size=1024, lr=5e-3, generator=g
    )
    assert sum(losses[-100:]) / 100 < 0.5 * sum(losses[:10]) / 10
    x_eval, _ = sq.sample_pairs(4000, torch.Generator().manual_seed(1))
    x_gen = ddpm_sample(
        model, s, x_eval.shape, cond=x_eval, generator=torch.Generator().manual_seed(2)
    )
    m = squ9_metrics(x_eval, x_gen, sq)
    assert m["coverage"] == 1.0, m["coverage_per_mode"]
    assert m["precision"] > E2E_PRECISION_BOUND, m["precision"]


# ----------------------------------------------------------------------------------------------
# v-prediction (Salimans & Ho 2022): the third parameterisation of chapter 1


@settings(max_examples=40, deadline=None)
@given(
    kind=st.sampled_from(KINDS),
    T=st.sampled_from(TS),
    frac=st.floats(0, 1),
    seed=st.integers(0, 2**31 - 1),
)
def test_v_conversions_invert_q_sample(kind, T, frac, seed):
    from minimdm.diffusion import predict_eps_from_v, predict_v, predict_x0_from_v

    s = NoiseSchedule(kind, T)
    t = min(int(frac * T), T - 1)
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randn(4, 3, generator=g, dtype=torch.float64)
    eps = torch.randn(4, 3, generator=g, dtype=torch.float64)
    x_t = q_sample(s, x0, t, noise=eps)
    v = predict_v(s, x0, t, eps)
    # v, x0, eps and x_t are a rotation of each other: both conversions are exact and bounded
    torch.testing.assert_close(predict_x0_from_v(s, x_t, t, v), x0, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(predict_eps_from_v(s, x_t, t, v), eps, rtol=1e-5, atol=1e-5)
    # an error in v reaches x0 shrunk by sqrt(1 - abar) <= 1
    err = predict_x0_from_v(s, x_t, t, v + 0.1) - x0
    assert err.abs().max() <= 0.1 + 1e-5


def test_v_prediction_loss_sampler_and_model():
    from minimdm.diffusion import ddim_sample, ddpm_sample, predict_v

    s = NoiseSchedule("cosine", 20)
    c = torch.tensor([[0.5, -1.0]]).expand(64, 2)

    def v_oracle(x_t, t, cond):  # knows the (constant) data: v from x_t and x0
        eps = predict_eps_from_x0(s, x_t, t, c[: len(x_t)])
        return predict_v(s, c[: len(x_t)], t, eps)

    loss, x0_hat = diffusion_loss(
        v_oracle, s, c, generator=torch.Generator().manual_seed(0), predicts="v"
    )
    assert loss.item() < 1e-8
    torch.testing.assert_close(x0_hat, c, rtol=1e-4, atol=1e-4)
    for sample in (ddpm_sample, ddim_sample):
        out = sample(v_oracle, s, (64, 2), predicts="v", generator=torch.Generator().manual_seed(1))
        torch.testing.assert_close(out, c, rtol=1e-3, atol=1e-3)
    net = MLPDenoiser(
        DenoiserConfig(x_dim=2, cond_dim=0, width=16, depth=2, time_dim=8, predicts="v")
    )
    assert net.predicts == "v"
    with pytest.raises(ValueError, match="predicts must be one of"):
        MLPDenoiser(
            DenoiserConfig(x_dim=2, cond_dim=0, width=16, depth=2, time_dim=8, predicts="mu")
        )
    with pytest.raises(ValueError, match="predicts must be one of"):
        diffusion_loss(v_oracle, s, c, predicts="mu")


@pytest.mark.parametrize("predicts", ["eps", "x0", "v"])
def test_min_snr_weights_each_level_as_an_error_on_x0(predicts):
    """Min-SNR-gamma (Hang et al. 2023): whatever the network predicts, level t's loss counts as
    min(SNR_t, gamma) times the squared error of the implied x0_hat."""
    s = NoiseSchedule("cosine", 20)
    torch.manual_seed(0)
    net = MLPDenoiser(DenoiserConfig(x_dim=3, cond_dim=0, width=16, depth=2, time_dim=8,
                                     predicts=predicts))  # fmt: skip
    x0 = torch.randn(64, 3)
    plain, x0_hat = diffusion_loss(
        net, s, x0, None, torch.Generator().manual_seed(1), predicts, reduce=False
    )
    weighted, _ = diffusion_loss(
        net, s, x0, None, torch.Generator().manual_seed(1), predicts, reduce=False, snr_gamma=5.0
    )
    t = torch.randint(0, s.T, (64,), generator=torch.Generator().manual_seed(1))  # the same draw
    snr = s.alphas_cumprod[t] / (1 - s.alphas_cumprod[t])
    x0_err = ((x0_hat - x0) ** 2).mean(1)
    torch.testing.assert_close(weighted, snr.clamp(max=5.0) * x0_err, rtol=1e-4, atol=1e-6)
    if predicts == "x0":
        torch.testing.assert_close(plain, x0_err)
    floored, _ = diffusion_loss(
        net, s, x0, None, torch.Generator().manual_seed(1), predicts, reduce=False, snr_gamma=5.0,
        snr_floor=1.0,
    )  # fmt: skip
    torch.testing.assert_close(floored, snr.clamp(1.0, 5.0) * x0_err, rtol=1e-4, atol=1e-6)


def test_skip_weights_are_the_best_linear_gain_on_the_noisy_frame():
    """c(t) of skip_weights is the regression slope of x_0 on x_t when x_0 ~ N(mu, sigma^2), and an
    x0-denoiser with a skip adds exactly c(t) x_t to its network's output."""
    from minimdm.amdm.models import skip_weights

    s = NoiseSchedule("cosine", 10)
    c = torch.tensor(skip_weights(s.alphas_cumprod, 0.3))
    g = torch.Generator().manual_seed(0)
    x0 = 2.0 + 0.3 * torch.randn(200_000, generator=g, dtype=torch.float64)
    for t in range(10):
        ab = s.alphas_cumprod[t].double()
        x_t = ab.sqrt() * x0 + (1 - ab).sqrt() * torch.randn(x0.shape, generator=g, dtype=x0.dtype)
        slope = torch.cov(torch.stack([x_t, x0]))[0, 1] / x_t.var()
        assert float(slope) == pytest.approx(float(c[t]), abs=0.01)
    cfg = DenoiserConfig(x_dim=3, cond_dim=2, width=8, depth=2, time_dim=4, predicts="x0",
                         skip=c.tolist())  # fmt: skip
    net = MLPDenoiser(cfg)
    torch.nn.init.zeros_(net.output.weight)
    torch.nn.init.zeros_(net.output.bias)
    x_t, t = torch.randn(5, 3), torch.tensor([0, 1, 4, 8, 9])
    torch.testing.assert_close(net(x_t, t, torch.randn(5, 2)), c[t][:, None] * x_t)
    with pytest.raises(ValueError, match="skip needs predicts='x0'"):
        MLPDenoiser(DenoiserConfig(3, 2, 8, 2, 4, "eps", skip=c.tolist()))


def test_a_root_only_skip_passes_the_noisy_frame_on_only_in_the_roots_velocity():
    """skip_features='root' adds c(t) x_t to d_x, d_y, d_r (the first three features) and nothing
    to the joints; the mask travels with the checkpoint's config."""
    from minimdm.amdm.train_config import TrainConfig, build_network

    cfg = TrainConfig(predicts="x0", skip_sigma=0.2, skip_features="root", T=6, width=8, depth=2)
    net = build_network(cfg, 15)
    assert net.config_dict()["skip_mask"] == [1.0] * 3 + [0.0] * 12
    torch.nn.init.zeros_(net.output.weight)
    torch.nn.init.zeros_(net.output.bias)
    x_t, t = torch.randn(4, 15), torch.tensor([0, 2, 3, 5])
    out = net(x_t, t, torch.randn(4, 15))
    torch.testing.assert_close(out[:, :3], net.skip[t][:, :3] * x_t[:, :3])
    assert bool((out[:, 3:] == 0).all()) and bool((net.skip[:, :3] > 0).all())
    with pytest.raises(ValueError, match="skip_features must be one of"):
        TrainConfig(predicts="x0", skip_sigma=0.2, skip_features="joints")
    with pytest.raises(ValueError, match="skip_mask must hold 3 zeros and ones"):
        MLPDenoiser(DenoiserConfig(3, 2, 8, 2, 4, "x0", skip=[0.5], skip_mask=[1.0, 0.5, 0.0]))


def test_the_roots_own_skip_spread_weights_its_three_features_and_leaves_the_joints_alone():
    """skip_sigma_root gives d_x, d_y, d_r the weights c(t) of their own spread, the joints keep
    skip_sigma's; without skip_sigma the joints get no skip at all."""
    from minimdm.amdm.train_config import TrainConfig, build_network
    from minimdm.diffusion import NoiseSchedule

    ac = NoiseSchedule("cosine", 6).alphas_cumprod
    root, joints = torch.tensor(skip_weights(ac, 0.2)), torch.tensor(skip_weights(ac, 0.06))
    for sigma, expect in ((0.06, joints), (0.0, torch.zeros(6))):
        cfg = TrainConfig(
            predicts="x0", skip_sigma=sigma, skip_sigma_root=0.2, T=6, width=8, depth=2
        )
        net = build_network(cfg, 15)
        torch.nn.init.zeros_(net.output.weight)
        torch.nn.init.zeros_(net.output.bias)
        x_t, t = torch.randn(4, 15), torch.tensor([0, 2, 3, 5])
        out = net(x_t, t, torch.randn(4, 15))
        torch.testing.assert_close(out[:, :3], root[t].float()[:, None] * x_t[:, :3])
        torch.testing.assert_close(out[:, 3:], expect[t].float()[:, None] * x_t[:, 3:])
    assert bool((root > joints).all())  # a wider spread passes more of the noisy frame on
    yaw = torch.tensor(skip_weights(ac, 0.4))
    cfg = TrainConfig(predicts="x0", skip_sigma=0.06, skip_sigma_yaw=0.4, T=6, width=8, depth=2)
    net = build_network(cfg, 15)  # the yaw rate alone gets its own spread; d_x, d_y the joints'
    expect = torch.cat(
        [joints[:, None].expand(6, 2), yaw[:, None], joints[:, None].expand(6, 12)], 1
    )
    torch.testing.assert_close(net.skip, expect.float())
    with pytest.raises(ValueError, match="skip_sigma_root needs predicts: x0"):
        TrainConfig(predicts="eps", skip_sigma_root=0.2)
    with pytest.raises(ValueError, match="skip_sigma_root must be a finite float"):
        TrainConfig(predicts="x0", skip_sigma_root=float("nan"))
