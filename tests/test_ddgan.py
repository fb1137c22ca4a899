"""Tests for minimdm.aamdm.model and minimdm.aamdm.train: schedules, the two ways of drawing
x_{t-1},
the combined sampler's step accounting, guidance, bad input, and short adversarial runs.

Closed forms are derived here from the forward process alone (Gaussian algebra), not from the
library's posterior code, so the tests check the maths.
"""

from __future__ import annotations

import math

import pytest
import torch

from minimdm.aamdm.model import (
    AAMDM,
    PAPER_BETAS,
    AAMDMConfig,
    DDGANDiscriminator,
    DDGANGenerator,
    DiscriminatorConfig,
    GeneratorConfig,
    Guide,
    StepCount,
    aamdm_betas,
    aamdm_sample,
    aamdm_schedule,
    q_posterior_sample,
    q_sample_pairs,
)
from minimdm.aamdm.train import (
    GANConfig,
    GANDivergedError,
    PolishConfig,
    pairs_to_windows,
    train_ddgan,
    train_polisher,
)
from minimdm.amdm.models import DenoiserConfig, MLPDenoiser
from minimdm.checkpoint import load_checkpoint, save_checkpoint
from minimdm.diffusion import DDGANStep, Handover, PolishStep, q_sample, reverse_chain
from minimdm.toy.squ9 import Squ9, squ9_metrics

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


# ----------------------------------------------------------------------------------------------
# Schedules


def _abar(betas):
    return [math.prod(1 - b for b in betas[: i + 1]) for i in range(len(betas))]


def test_paper_schedule_is_exact():
    assert aamdm_betas(3, 2) == pytest.approx(list(PAPER_BETAS), rel=1e-12)
    s = aamdm_schedule(3, 2)
    assert s.T == 5
    assert s.betas.tolist() == pytest.approx(list(PAPER_BETAS), rel=1e-6)


@pytest.mark.parametrize("T_gan", [1, 2, 3, 4, 10])
@pytest.mark.parametrize("T_adm", [0, 1, 2, 3])
def test_ablation_schedules_keep_the_hand_over_and_the_end(T_gan, T_adm):
    b = aamdm_betas(T_gan, T_adm)
    assert len(b) == T_gan + T_adm
    assert all(0 < x < 1 for x in b)
    ab = _abar(b)
    paper = _abar(PAPER_BETAS)
    # the polishing levels end at the paper's hand-over level, whatever T_adm
    if T_adm > 0:
        assert ab[T_adm - 1] == pytest.approx(paper[1], rel=1e-9)
        assert b[:T_adm] == sorted(b[:T_adm])  # noise grows with the level
    # the last level is the paper's nearly pure noise, whatever T_gan
    assert ab[-1] / (ab[T_adm - 1] if T_adm else 1.0) == pytest.approx(paper[-1] / paper[1])


@pytest.mark.parametrize("bad", [(0, 2), (-1, 2), (3, -1), (2.5, 2)])
def test_invalid_step_counts_raise(bad):
    with pytest.raises(ValueError, match="T_gan|T_adm"):
        aamdm_betas(*bad)


# ----------------------------------------------------------------------------------------------
# The posterior sampling used by the discriminator


@pytest.mark.parametrize("t", [0, 1, 2, 3, 4])
def test_real_pairs_and_posterior_draws_have_the_same_joint_law(t):
    """Real pairs (forward: x_{t-1} | x0, then x_t | x_{t-1}) and posterior pairs (x_t | x0,
    then x_{t-1} ~ q(x_{t-1} | x_t, x0)) must have the same Gaussian law given x0.

    Closed form from the forward process: with a = abar_{t-1} (1 at t = 0),
    E[x_{t-1}] = sqrt(a) x0, Var[x_{t-1}] = 1 - a, Var[x_t] = 1 - abar_t,
    Cov[x_{t-1}, x_t] = sqrt(alpha_t) (1 - a).
    """
    s = aamdm_schedule(3, 2)
    n = 200_000
    x0 = torch.full((n, 1), 0.7)
    tt = torch.full((n,), t)
    g = torch.Generator().manual_seed(t)
    prev_f, xt_f = q_sample_pairs(s, x0, tt, g)
    xt_p = q_sample(s, x0, tt, generator=g)
    prev_p = q_posterior_sample(s, x0, xt_p, tt, g)

    betas = [float(b) for b in s.betas]
    ab = _abar(betas)
    a = ab[t - 1] if t > 0 else 1.0
    alpha = 1 - betas[t]
    expect = {
        "mean_prev": math.sqrt(a) * 0.7,
        "mean_t": math.sqrt(ab[t]) * 0.7,
        "var_prev": 1 - a,
        "var_t": 1 - ab[t],
        "cov": math.sqrt(alpha) * (1 - a),
    }
    for prev, xt in ((prev_f, xt_f), (prev_p, xt_p)):
        p, q = prev[:, 0].double(), xt[:, 0].double()
        got = {
            "mean_prev": p.mean().item(),
            "mean_t": q.mean().item(),
            "var_prev": p.var().item(),
            "var_t": q.var().item(),
            "cov": ((p - p.mean()) * (q - q.mean())).mean().item(),
        }
        for k in expect:
            assert got[k] == pytest.approx(expect[k], abs=6e-3), k


def test_posterior_at_level_zero_returns_x0():
    s = aamdm_schedule(3, 2)
    x0, xt = torch.randn(5, 3), torch.randn(5, 3)
    out = q_posterior_sample(s, x0, xt, 0, torch.Generator().manual_seed(0))
    assert torch.allclose(out, x0, atol=1e-6)


def test_real_pairs_reject_levels_outside_the_schedule():
    s = aamdm_schedule(3, 2)
    with pytest.raises(ValueError, match=r"levels in \[0, 4\]"):
        q_sample_pairs(s, torch.zeros(2, 2), torch.tensor([0, 5]))


# ----------------------------------------------------------------------------------------------
# The combined sampler: step accounting, hook, guidance, bad input


class Recorder(torch.nn.Module):
    """Wraps a network and records the step indices it is called with."""

    def __init__(self, net):
        super().__init__()
        self.net, self.calls, self.outputs = net, [], []
        self.config = getattr(net, "config", None)

    def forward(self, x, t, cond, *rest):
        self.calls.append(int(t[0]))
        out = self.net(x, t, cond, *rest)
        self.outputs.append(out)
        return out


def tiny_aamdm(T_gan=3, T_adm=2, x_dim=2, seed=0, **kw) -> AAMDM:
    torch.manual_seed(seed)
    cfg = AAMDMConfig(x_dim, x_dim, T_gan, T_adm, latent_dim=3, width=16, depth=2, time_dim=8)
    for k, v in kw.items():
        setattr(cfg, k, v)
    return AAMDM(cfg).eval()


def test_sampler_step_accounting_three_plus_two():
    m = tiny_aamdm()
    gan, pol = Recorder(m.generator), Recorder(m.polisher)
    hooked = []

    def hook(t, x, x0):
        hooked.append(t)
        return x

    count = StepCount()
    cond = torch.randn(6, 2)
    out = aamdm_sample(
        gan, pol, m.schedule(), (6, 2), cond, 3, 2, torch.Generator().manual_seed(0), hook,
        count=count,
    )  # fmt: skip
    assert count.levels == [4, 3, 2, 1, 0]
    assert count.modules == ["gan", "gan", "gan", "adm", "adm"]
    assert (count.gan_steps, count.adm_steps, count.network_calls) == (3, 2, 5)
    assert gan.calls == [2, 1, 0]  # the generator sees its own step index t - T_adm
    assert pol.calls == [1, 0]
    assert hooked == [3, 2, 1, 0, -1]
    assert torch.equal(out, pol.outputs[-1])  # the last step returns the polisher's x0


def test_sampler_without_polishing_returns_the_gan_draft():
    m = tiny_aamdm()
    gan = Recorder(m.generator)
    count = StepCount()
    out = aamdm_sample(gan, None, m.schedule(), (4, 2), torch.zeros(4, 2), 3, 0, count=count)
    assert count.levels == [4, 3, 2] and count.modules == ["gan"] * 3
    assert torch.equal(out, gan.outputs[-1])
    # the model's own sampler counts the same way
    c2 = StepCount()
    m.sample(torch.zeros(4, 2), T_adm=0, count=c2)
    assert c2.network_calls == 3


def test_sampler_is_reproducible_and_batch_consistent():
    m = tiny_aamdm()
    cond = torch.randn(8, 2)
    a = m.sample(cond, torch.Generator().manual_seed(3))
    b = m.sample(cond, torch.Generator().manual_seed(3))
    assert torch.equal(a, b) and torch.isfinite(a).all()


@pytest.mark.parametrize(
    "T_gan,T_adm,match",
    [(3, 1, "must equal the schedule's T = 5"), (2, 2, "must equal"), (6, 0, "must equal")],
)
def test_sampler_rejects_step_counts_that_do_not_match_the_schedule(T_gan, T_adm, match):
    m = tiny_aamdm()
    with pytest.raises(ValueError, match=match):
        aamdm_sample(m.generator, m.polisher, m.schedule(), (2, 2), torch.zeros(2, 2), T_gan, T_adm)


def test_sampler_rejects_zero_steps_missing_polisher_bad_shapes_and_nan():
    m = tiny_aamdm()
    s, c = m.schedule(), torch.zeros(2, 2)
    with pytest.raises(ValueError, match="T_gan must be an integer >= 1"):
        aamdm_sample(m.generator, m.polisher, s, (2, 2), c, 0, 5)
    with pytest.raises(ValueError, match="need a polisher"):
        aamdm_sample(m.generator, None, s, (2, 2), c, 3, 2)
    with pytest.raises(ValueError, match=r"shape must be \(B, 2\)"):
        aamdm_sample(m.generator, m.polisher, s, (2, 5), c, 3, 2)
    with pytest.raises(ValueError, match="cond must be finite"):
        aamdm_sample(m.generator, m.polisher, s, (2, 2), torch.tensor([[0.0, math.nan]] * 2))
    with pytest.raises(ValueError, match=r"cond must have shape \(2, 2\)"):
        m.generator(torch.zeros(2, 2), torch.zeros(2, dtype=torch.long), torch.zeros(2, 7),
                    torch.zeros(2, 3))  # fmt: skip
    with pytest.raises(ValueError, match="betas must hold T_gan \\+ T_adm = 3 \\+ 2 = 5"):
        AAMDMConfig(2, 2, 3, 2, betas=[0.1, 0.2])


class ShiftNet(torch.nn.Module):
    """x0_hat = x_t + 0.1 r (generator) or x_t (polisher): a Jacobian of the identity."""

    def __init__(self, latent_dim=None):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(()))
        if latent_dim:
            self.config = GeneratorConfig(2, 2, latent_dim=latent_dim)

    def forward(self, x, t, cond, r=None):
        return x + self.w + (0.1 * r[:, :2] if r is not None else 0)


def test_guidance_follows_eq_13():
    """x0* = x0 - eps alpha_t dJ/dx_t; with dx0/dx_t = I and J = |x0 - c|^2 the first step moves
    x0 by -2 eps alpha_t (x0 - c), and the guided samples end closer to c."""
    gan, pol = ShiftNet(latent_dim=2), ShiftNet()
    s = aamdm_schedule(3, 2)
    target = torch.tensor([2.0, -1.0])

    def cost(x0):
        return ((x0 - target) ** 2).sum(-1)

    def run(guide):
        seen = []
        out = aamdm_sample(
            gan, pol, s, (64, 2), torch.zeros(64, 2), generator=torch.Generator().manual_seed(1),
            hook=lambda t, x, x0: seen.append(x0) or x, guide=guide,
        )  # fmt: skip
        return out, seen

    plain, seen_p = run(None)
    guided, seen_g = run(Guide(cost, scale=0.3))
    alpha = float(s.alphas[4])
    assert torch.allclose(seen_g[0], seen_p[0] - 0.3 * alpha * 2 * (seen_p[0] - target), atol=1e-5)
    assert cost(guided).mean() < 0.5 * cost(plain).mean()
    m = tiny_aamdm()
    with pytest.raises(ValueError, match=r"guide.cost must return shape \(3,\)"):
        m.sample(torch.zeros(3, 2), guide=Guide(lambda x: x, 1.0))


def test_checkpoint_round_trip_reproduces_samples(tmp_path):
    m = tiny_aamdm(fourier=4)
    save_checkpoint(tmp_path / "ddgan", m, {"step": 0})
    ck = load_checkpoint(tmp_path / "ddgan")
    assert ck.kind == "ddgan"
    cond = torch.randn(5, 2)
    a = m.sample(cond, torch.Generator().manual_seed(0))
    b = ck.model.sample(cond, torch.Generator().manual_seed(0))
    assert torch.equal(a, b)


# ----------------------------------------------------------------------------------------------
# Training


@pytest.fixture(scope="module")
def squ9_data():
    sq = Squ9()
    g = torch.Generator().manual_seed(0)
    xp, xn = sq.sample_pairs(4000, g)
    xe, _ = sq.sample_pairs(1000, torch.Generator().manual_seed(1))
    return sq, xp, xn, xe


def _small(fourier=8):
    torch.manual_seed(0)
    m = AAMDM(AAMDMConfig(2, 2, 3, 2, latent_dim=4, width=64, depth=3, time_dim=16,
                          fourier=fourier))  # fmt: skip
    d = DDGANDiscriminator(DiscriminatorConfig(2, 2, 64, 3, 16, fourier=fourier))
    return m, d


def test_short_adversarial_run_on_squ9_does_not_diverge(squ9_data):
    """300 steps on Squ-9: finite losses, a discriminator that neither wins nor loses outright,
    and samples that moved from the untrained generator's blob towards the 9 modes."""
    sq, xp, xn, xe = squ9_data
    m, d = _small()
    before = squ9_metrics(xe, m.sample(xe, torch.Generator().manual_seed(2), T_adm=0))
    cfg = GANConfig(steps=300, batch_size=128, lr_g=1e-3, lr_d=2e-3, r1_gamma=0.1)
    hist = train_ddgan(m.generator, d, m.schedule(), pairs_to_windows(xp, xn), 3, cfg)
    assert len(hist) == 300
    assert all(math.isfinite(h["loss_d"]) and math.isfinite(h["loss_g"]) for h in hist)
    late = hist[-50:]
    d_real = sum(h["d_real"] for h in late) / len(late)
    d_fake = sum(h["d_fake"] for h in late) / len(late)
    assert 0.2 < d_fake < d_real < 0.8, (d_real, d_fake)
    out = m.sample(xe, torch.Generator().manual_seed(2), T_adm=0)
    after = squ9_metrics(xe, out)
    assert torch.isfinite(out).all() and out.abs().max() < 3
    assert after["transition_tv"] < before["transition_tv"]
    assert after["coverage"] > before["coverage"]


def test_polisher_training_reduces_the_rollout_loss(squ9_data):
    sq = squ9_data[0]
    seq = sq.sample_sequence(5, 500, torch.Generator().manual_seed(0))  # (500, 5, 2)
    torch.manual_seed(0)
    pol = MLPDenoiser(DenoiserConfig(2, 2, 32, 3, 16, "x0"))
    hist = train_polisher(pol, aamdm_schedule(3, 2), seq, 2, PolishConfig(150, 64, 3e-3))
    first = sum(h["loss"] for h in hist[:10]) / 10
    last = sum(h["loss"] for h in hist[-10:]) / 10
    assert last < 0.2 * first
    with pytest.raises(ValueError, match=r"T_adm must lie in \[1, T=5\]"):
        train_polisher(pol, aamdm_schedule(3, 2), seq, 0)
    with pytest.raises(ValueError, match="windows must be finite"):
        train_polisher(pol, aamdm_schedule(3, 2), seq * math.nan, 2)


def test_divergence_stops_with_a_message_and_keeps_the_last_good_checkpoint(tmp_path, squ9_data):
    _, xp, xn, _ = squ9_data
    m, d = _small()
    cfg = GANConfig(steps=60, batch_size=32, ckpt_interval=20)

    def poison(step, record):
        if step == 30:  # a NaN creeps into the generator after step 30
            with torch.no_grad():
                m.generator.output.weight.fill_(math.nan)

    ckpt = tmp_path / "gan"
    ckpt.mkdir()
    with pytest.raises(GANDivergedError, match=r"diverged at step 31.*step 20\) is kept at"):
        train_ddgan(m.generator, d, m.schedule(), pairs_to_windows(xp, xn), 3, cfg,
                    checkpoint=ckpt, bundle=m, callback=poison)  # fmt: skip
    good = load_checkpoint(ckpt)
    assert good.step == 20
    assert all(torch.isfinite(p).all() for p in good.model.parameters())
    assert torch.isfinite(good.model.sample(torch.zeros(3, 2))).all()


def test_gan_training_resumes_bit_for_bit(tmp_path, squ9_data):
    _, xp, xn, _ = squ9_data
    w = pairs_to_windows(xp, xn)
    full, d_full = _small()
    train_ddgan(full.generator, d_full, full.schedule(), w, 3, GANConfig(steps=40, batch_size=32))

    part, d_part = _small()
    ckpt = tmp_path / "run"
    ckpt.mkdir()
    cfg = GANConfig(steps=40, batch_size=32, ckpt_interval=20)

    def crash(step, record):
        if step == 25:
            raise KeyboardInterrupt  # killed after the checkpoint of step 20

    with pytest.raises(KeyboardInterrupt):
        train_ddgan(part.generator, d_part, part.schedule(), w, 3, cfg, checkpoint=ckpt,
                    bundle=part, callback=crash)  # fmt: skip
    again, d_again = _small()
    train_ddgan(again.generator, d_again, again.schedule(), w, 3, cfg, checkpoint=ckpt,
                bundle=again)  # fmt: skip
    for a, b in zip(full.generator.parameters(), again.generator.parameters(), strict=True):
        assert torch.equal(a, b)


def test_generator_uses_its_latent():
    """Different r, same x_t and condition: different x0 (the step is multimodal)."""
    torch.manual_seed(0)
    g = DDGANGenerator(GeneratorConfig(2, 2, latent_dim=4, width=16, depth=2, time_dim=8))
    x, c, t = torch.zeros(2, 2), torch.zeros(2, 2), torch.zeros(2, dtype=torch.long)
    out = g(x, t, c, torch.randn(2, 4, generator=torch.Generator().manual_seed(0)))
    assert (out[0] - out[1]).abs().max() > 1e-3


# ----------------------------------------------------------------------------------------------
# The sampler is the library's reverse chain with DD-GAN and polishing step rules


def test_sampler_is_the_reverse_chain_with_a_handover():
    m = tiny_aamdm()
    s, cond = m.schedule(), torch.randn(4, 2)
    rule = Handover(
        DDGANStep(m.generator, s, m.config.latent_dim, t_offset=2), PolishStep(m.polisher, s), 2
    )
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    x = torch.randn(4, 2, generator=g1)
    direct = reverse_chain(rule, x, range(4, -1, -1), cond, g1)
    assert torch.equal(aamdm_sample(m.generator, m.polisher, s, (4, 2), cond, generator=g2), direct)


def test_guidance_runs_before_the_per_feature_clamp():
    """Guidance (an x0 hook) pulls towards a far target; the clamp (the next x0 hook) still
    bounds every estimate, and the final sample, to the per-feature range."""
    gan, pol = ShiftNet(latent_dim=2), ShiftNet()
    s = aamdm_schedule(3, 2)
    lo, hi = torch.tensor([-0.5, -2.0]), torch.tensor([0.25, 1.0])
    seen = []
    out = aamdm_sample(
        gan, pol, s, (32, 2), torch.zeros(32, 2), generator=torch.Generator().manual_seed(0),
        hook=lambda t, x, x0: seen.append(x0) or x, clip_x0=(lo, hi),
        guide=Guide(lambda x0: ((x0 - torch.tensor([5.0, 5.0])) ** 2).sum(-1), scale=2.0),
    )  # fmt: skip
    for x0 in seen:
        assert (x0 >= lo).all() and (x0 <= hi).all()
    assert torch.equal(out, seen[-1])
    assert (out == hi).float().mean() > 0.5  # the guide pushed most estimates to the upper bound


def test_config_clamp_is_checked_and_survives_a_checkpoint(tmp_path):
    with pytest.raises(ValueError, match=r"clip_x0 must be a pair \(lo, hi\) of 2 values"):
        AAMDMConfig(2, 2, 3, 2, clip_x0=[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="clip_x0 must have lo <= hi"):
        AAMDMConfig(2, 2, 3, 2, clip_x0=[[0.0, 2.0], [1.0, 1.0]])
    cfg = AAMDMConfig(2, 2, 3, 2, latent_dim=3, width=16, depth=2, time_dim=8,
                      clip_x0=(torch.tensor([-0.1, -0.2]), torch.tensor([0.1, 0.3])))  # fmt: skip
    assert cfg.clip_x0 == [[pytest.approx(-0.1), pytest.approx(-0.2)],
                           [pytest.approx(0.1), pytest.approx(0.3)]]  # fmt: skip
    torch.manual_seed(0)
    m = AAMDM(cfg).eval()
    save_checkpoint(tmp_path / "ddgan", m, {"step": 0})
    ck = load_checkpoint(tmp_path / "ddgan")
    assert ck.model.config.clip_x0 == cfg.clip_x0
    out = ck.model.sample(torch.randn(64, 2), torch.Generator().manual_seed(1))
    assert (out >= torch.tensor([-0.1, -0.2])).all() and (out <= torch.tensor([0.1, 0.3])).all()
