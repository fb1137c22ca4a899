"""Tests for AAMDM's two pair constructions and the training options (minimdm.aamdm.train).

The distributions of the pairs are checked against closed forms of the forward process
(Gaussian algebra, written out here), with stub networks that return constants, so that a real
pair built from the polisher's output and one built from the data can be told apart.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from minimdm.aamdm.model import (
    AAMDM,
    AAMDMConfig,
    DDGANDiscriminator,
    DDGANGenerator,
    DiscriminatorConfig,
    GeneratorConfig,
    aamdm_schedule,
)
from minimdm.aamdm.train import (
    OPTIMIZERS,
    PAIRS,
    GANConfig,
    PolishConfig,
    draw_gan_pairs,
    pairs_to_windows,
    train_ddgan,
    train_polisher,
)
from minimdm.studies.aamdm_variants import (
    METRICS,
    VariantsConfig,
    compare_pairs,
    describe,
    read_results,
    summarize,
)
from minimdm.studies.squ9_acceleration import Squ9StudyConfig
from minimdm.toy.squ9 import Squ9


@pytest.fixture(autouse=True)
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


class Const(nn.Module):
    """A polisher or generator stub whose clean estimate is always ``value``."""

    def __init__(self, value: float, latent_dim: int = 1) -> None:
        super().__init__()
        self.value = value
        self.w = nn.Parameter(torch.zeros(()))
        self.config = SimpleNamespace(latent_dim=latent_dim)
        self.calls = 0

    def forward(self, x_t, t, cond, r=None):
        self.calls += 1
        return torch.full_like(x_t, self.value) + 0 * self.w


DATA, POLISHED, GENERATED = 1.5, -0.8, 0.4
N = 120_000


def _pairs(pairs: str, n: int = N, h: int = 1, polisher=None, T_adm=None):
    sched = aamdm_schedule(3, 2)
    windows = torch.full((n, h + 1, 1), DATA)
    g = torch.Generator().manual_seed(0)
    pol = Const(POLISHED) if polisher is None else polisher
    p = draw_gan_pairs(Const(GENERATED), sched, windows, 3, g, pairs, pol, T_adm)
    return sched, p


def _moments(sched, p, level_of_k):
    """Per GAN level: means of x_prev_real, x_prev_fake, their variances, cov(fake, x_t)."""
    out = {}
    for k in range(3):
        t = level_of_k(k)
        sel = p.k == k
        real, fake, xt = p.x_prev_real[sel, 0], p.x_prev_fake[sel, 0], p.x_t[sel, 0]
        cov = ((fake - fake.mean()) * (xt - xt.mean())).mean()
        cov_real = ((real - real.mean()) * (xt - xt.mean())).mean()
        out[t] = dict(
            real=(real.mean().item(), real.var().item()),
            fake=(fake.mean().item(), fake.var().item()),
            xt=(xt.mean().item(), xt.var().item()),
            cov=cov.item(),
            cov_real=cov_real.item(),
            n=int(sel.sum()),
        )
    return out


def _abar(sched, t):  # \bar\alpha_t, with \bar\alpha_{-1} = 1 (clean)
    return 1.0 if t < 0 else float(sched.alphas_cumprod[t])


def test_paper_pairs_diffuse_the_polishers_output_and_the_generators_x0():
    """Algorithm 1 line 20: real x^{t-1} ~ N(sqrt(abar_{t-1}) c, 1 - abar_{t-1}) with c the
    polisher's output (not the data); line 21: x^t one forward step from it; line 24: the fake
    x^{t-1} ~ N(sqrt(abar_{t-1}) g, 1 - abar_{t-1}) with g the generator's x0, independent of
    x^t."""
    sched, p = _pairs("paper")
    assert torch.equal(p.x0_real, torch.full_like(p.x0_real, POLISHED))
    assert torch.equal(p.x0_fake, torch.full_like(p.x0_fake, GENERATED))
    m = _moments(sched, p, lambda k: k + 2)
    for t, s in m.items():
        ab_prev, ab = _abar(sched, t - 1), _abar(sched, t)
        tol = 6 / math.sqrt(s["n"])
        assert s["real"][0] == pytest.approx(math.sqrt(ab_prev) * POLISHED, abs=tol)
        assert s["real"][1] == pytest.approx(1 - ab_prev, abs=tol + 0.02 * (1 - ab_prev))
        assert s["xt"][0] == pytest.approx(math.sqrt(ab) * POLISHED, abs=tol)
        assert s["xt"][1] == pytest.approx(1 - ab, abs=tol + 0.02)
        # Cov(x^{t-1}, x^t) = sqrt(alpha_t) Var(x^{t-1}) for the real, forward pair
        alpha = float(sched.alphas[t])
        assert s["cov_real"] == pytest.approx(math.sqrt(alpha) * (1 - ab_prev), abs=tol + 0.02)
        assert s["fake"][0] == pytest.approx(math.sqrt(ab_prev) * GENERATED, abs=tol)
        assert s["fake"][1] == pytest.approx(1 - ab_prev, abs=tol + 0.02 * (1 - ab_prev))
        assert abs(s["cov"]) < tol  # line 24 ignores x^t


def test_ddgan_pairs_diffuse_the_data_and_draw_fakes_from_the_posterior():
    """The default: real pairs from the data; the fake x^{t-1} from q(x^{t-1} | x^t, x0_gen),
    whose mean is the posterior mean (Ho et al. eq. 7), so it covaries with x^t."""
    sched, p = _pairs("ddgan")
    assert torch.equal(p.x0_real, torch.full_like(p.x0_real, DATA))
    m = _moments(sched, p, lambda k: k + 2)
    for t, s in m.items():
        ab_prev, ab = _abar(sched, t - 1), _abar(sched, t)
        beta, alpha = float(sched.betas[t]), float(sched.alphas[t])
        tol = 6 / math.sqrt(s["n"])
        assert s["real"][0] == pytest.approx(math.sqrt(ab_prev) * DATA, abs=tol)
        # posterior mean: c0 x0 + ct x_t, with the closed-form coefficients
        c0 = math.sqrt(ab_prev) * beta / (1 - ab)
        ct = math.sqrt(alpha) * (1 - ab_prev) / (1 - ab)
        want = c0 * GENERATED + ct * s["xt"][0]
        assert s["fake"][0] == pytest.approx(want, abs=tol)
        assert s["cov"] == pytest.approx(ct * s["xt"][1], abs=tol + 0.02)
        if t == 3:  # elsewhere 1 - abar_{t-1} or alpha_t is tiny, and so is the covariance
            assert s["cov"] > 0.05


def test_paper_conditions_are_the_polishers_rollout_and_data_stand_in_without_polishing():
    """Line 23's condition x̂z^0_{k-1}: frame 0 is the data, later frames the polisher's
    rollout; with T_adm = 0 there is no polisher and the data are the real pairs' x0."""
    pol = Const(POLISHED)
    sched, p = _pairs("paper", n=50, h=3, polisher=pol)
    cond = p.cond.reshape(50, 3, 1)
    assert torch.equal(cond[:, 0], torch.full((50, 1), DATA))
    assert torch.equal(cond[:, 1:], torch.full((50, 2, 1), POLISHED))
    assert torch.equal(p.x0_real, torch.full((150, 1), POLISHED))
    assert pol.calls == 3  # one polisher call per frame of the window
    # T_adm = 0: the whole schedule is the GAN's; no polisher needed, the data are used
    sched0 = aamdm_schedule(3, 0)
    windows = torch.full((40, 2, 1), DATA)
    p0 = draw_gan_pairs(
        Const(GENERATED), sched0, windows, 3, torch.Generator().manual_seed(0), "paper", None
    )
    assert torch.equal(p0.x0_real, torch.full((40, 1), DATA))


def test_paper_pairs_without_a_polisher_raise():
    sched = aamdm_schedule(3, 2)
    windows = torch.zeros(8, 2, 2)
    gan = Const(0.0)
    with pytest.raises(ValueError, match=r"pairs='paper'.*polisher"):
        draw_gan_pairs(gan, sched, windows, 3, None, "paper", None)
    torch.manual_seed(0)
    m = AAMDM(AAMDMConfig(2, 2, 3, 2, latent_dim=2, width=16, depth=2, time_dim=8))
    d = DDGANDiscriminator(DiscriminatorConfig(2, 2, 16, 2, 8))
    with pytest.raises(ValueError, match=r"pairs='paper'.*polisher="):
        train_ddgan(m.generator, d, m.schedule(), windows, 3, GANConfig(steps=1, pairs="paper"))


@pytest.mark.parametrize(
    "make, option, allowed",
    [
        (lambda: GANConfig(pairs="xiao"), "pairs", PAIRS),
        (lambda: GANConfig(optimizer="sgd"), "optimizer", OPTIMIZERS),
        (lambda: PolishConfig(optimizer="adamw"), "optimizer", OPTIMIZERS),
        (lambda: DDGANGenerator(GeneratorConfig(2, 2, activation="relu")), "activation",
         ("silu", "mish")),
        (lambda: DDGANDiscriminator(DiscriminatorConfig(2, 2, activation="gelu")), "activation",
         ("leaky_relu", "silu", "mish")),
        (lambda: draw_gan_pairs(Const(0.0), aamdm_schedule(3, 2), torch.zeros(2, 2, 1), 3,
                                pairs="posterior"), "pairs", PAIRS),
    ],
)  # fmt: skip
def test_bad_option_values_name_the_option_and_the_allowed_values(make, option, allowed):
    with pytest.raises(ValueError) as err:
        make()
    msg = str(err.value)
    assert msg.startswith(f"{option} must be one of")
    assert all(repr(a) in msg for a in allowed), msg


def test_activation_option_really_changes_the_networks_but_not_their_weights():
    """Mish nets hold the same parameters as the default ones (checkpoints load either way),
    call nn.Mish in forward, and compute something else with the same weights."""
    torch.manual_seed(0)
    for Net, Cfg, default in (
        (DDGANGenerator, GeneratorConfig, "silu"),
        (DDGANDiscriminator, DiscriminatorConfig, "leaky_relu"),
    ):
        base = Net(Cfg(2, 2, width=16, depth=3, time_dim=8))
        assert base.config.activation == default
        mish = Net(Cfg(2, 2, width=16, depth=3, time_dim=8, activation="mish"))
        mish.load_state_dict(base.state_dict())  # same keys, same shapes
        calls = []
        for mod in mish.modules():
            if isinstance(mod, nn.Mish):
                mod.register_forward_hook(lambda *a, calls=calls: calls.append(1))
        assert not any(isinstance(mod, nn.Mish) for mod in base.modules())
        x, c = torch.randn(5, 2), torch.randn(5, 2)
        t = torch.tensor([0, 1, 2, 0, 1])
        if Net is DDGANGenerator:
            r = torch.randn(5, 8)
            a, b = base(x, t, c, r), mish(x, t, c, r)
        else:
            a, b = base(x, x, c, t), mish(x, x, c, t)
        assert calls, "nn.Mish was never called"
        assert not torch.allclose(a, b)


def test_radam_option_builds_radam_for_every_network(monkeypatch):
    made = []

    class SpyRAdam(torch.optim.RAdam):
        def __init__(self, params, **kw):
            made.append(kw)
            super().__init__(params, **kw)

    monkeypatch.setattr(torch.optim, "RAdam", SpyRAdam)
    torch.manual_seed(0)
    m = AAMDM(AAMDMConfig(2, 2, 3, 2, latent_dim=2, width=16, depth=2, time_dim=8))
    d = DDGANDiscriminator(DiscriminatorConfig(2, 2, 16, 2, 8))
    seq = Squ9().sample_sequence(3, 64, torch.Generator().manual_seed(0))
    train_polisher(m.polisher, m.schedule(), seq, 2, PolishConfig(2, 8, optimizer="radam"))
    assert len(made) == 1
    train_ddgan(m.generator, d, m.schedule(), seq, 3, GANConfig(steps=2, batch_size=8),
                polisher=m.polisher)  # fmt: skip
    assert len(made) == 1  # the default stays Adam
    cfg = GANConfig(steps=2, batch_size=8, optimizer="radam", ema_decay=0)
    train_ddgan(m.generator, d, m.schedule(), seq, 3, cfg, polisher=m.polisher)
    assert len(made) == 3 and {kw["betas"] for kw in made[1:]} == {(0.5, 0.9)}


@pytest.fixture(scope="module")
def squ9_trained_polisher():
    sq = Squ9()
    g = torch.Generator().manual_seed(0)
    xp, xn = sq.sample_pairs(1000, g)
    torch.manual_seed(0)
    m = AAMDM(AAMDMConfig(2, 2, 3, 2, latent_dim=4, width=48, depth=3, time_dim=16, fourier=8))
    train_polisher(m.polisher, m.schedule(), pairs_to_windows(xp, xn), 2, PolishConfig(20, 32))
    return xp, xn, m


@pytest.mark.parametrize("pairs", PAIRS)
def test_a_short_run_of_each_variant_stays_finite_and_learns(pairs, squ9_trained_polisher):
    """Each construction trains: finite losses and samples, the generator moves, and the frozen
    polisher is left untouched."""
    xp, xn, base = squ9_trained_polisher
    torch.manual_seed(1)
    m = AAMDM(AAMDMConfig(2, 2, 3, 2, latent_dim=4, width=48, depth=3, time_dim=16, fourier=8))
    m.polisher.load_state_dict(base.polisher.state_dict())
    pol_before = {k: v.clone() for k, v in m.polisher.state_dict().items()}
    gen_before = {k: v.clone() for k, v in m.generator.state_dict().items()}
    d = DDGANDiscriminator(DiscriminatorConfig(2, 2, 48, 3, 16, fourier=8))
    cfg = GANConfig(steps=30, batch_size=32, lr_g=1e-3, lr_d=2e-3, r1_gamma=0.1, pairs=pairs)
    hist = train_ddgan(m.generator, d, m.schedule(), pairs_to_windows(xp, xn), 3, cfg,
                       polisher=m.polisher)  # fmt: skip
    assert all(math.isfinite(h["loss_d"]) and math.isfinite(h["loss_g"]) for h in hist)
    assert all(torch.equal(v, m.polisher.state_dict()[k]) for k, v in pol_before.items())
    assert any(not torch.equal(v, m.generator.state_dict()[k]) for k, v in gen_before.items())
    out = m.sample(xp[:200], torch.Generator().manual_seed(0))
    assert torch.isfinite(out).all()


def test_the_two_variants_train_differently_and_ddgan_ignores_the_polisher_on_pairs(
    squ9_trained_polisher,
):
    """On pairs (h = 1) DD-GAN's construction never calls the polisher, so passing one leaves
    training bit for bit the same; Algorithm 1's uses it and ends elsewhere."""
    xp, xn, base = squ9_trained_polisher
    w = pairs_to_windows(xp[:500], xn[:500])
    out = {}
    for name, pairs, pol in (
        ("ddgan", "ddgan", None),
        ("ddgan+pol", "ddgan", base.polisher),
        ("paper", "paper", base.polisher),
    ):
        torch.manual_seed(2)
        m = AAMDM(AAMDMConfig(2, 2, 3, 2, latent_dim=2, width=16, depth=2, time_dim=8))
        d = DDGANDiscriminator(DiscriminatorConfig(2, 2, 16, 2, 8))
        train_ddgan(m.generator, d, m.schedule(), w, 3,
                    GANConfig(steps=5, batch_size=16, pairs=pairs), polisher=pol)  # fmt: skip
        out[name] = torch.cat([p.flatten() for p in m.generator.parameters()])
    assert torch.equal(out["ddgan"], out["ddgan+pol"])
    assert not torch.equal(out["ddgan"], out["paper"])


# ----------------------------------------------------------------------------------------------
# The study harness


def test_compare_pairs_runs_both_variants_per_seed_and_summarizes(tmp_path):
    study = Squ9StudyConfig(n_train=400, n_eval=200, window=2, width=16, depth=2, fourier=4)
    cfg = VariantsConfig(seeds=(0, 1), gan_steps=3, polish_steps=2, repeats=1, study=study)
    rows = compare_pairs(cfg)
    assert [(r["seed"], r["variant"]) for r in rows] == [
        (0, "ddgan"), (0, "paper"), (1, "ddgan"), (1, "paper")
    ]  # fmt: skip
    for r in rows:
        assert r["network_calls"] == 5
        assert all(math.isfinite(r[m]) for m in METRICS)
    # one polisher per seed, shared by both variants
    assert rows[0]["polish_train_s"] == rows[1]["polish_train_s"]
    summary = summarize(rows)
    assert [s["variant"] for s in summary] == ["ddgan", "paper", "paper-ddgan"]
    for m in METRICS:
        vals = [r[m] for r in rows if r["variant"] == "paper"]
        assert summary[1][m][0] == pytest.approx(sum(vals) / 2)
        diffs = [rows[i + 1][m] - rows[i][m] for i in (0, 2)]
        assert summary[2][m][0] == pytest.approx(sum(diffs) / 2)
    text = describe(summary)
    assert len(text.splitlines()) == len(METRICS)
    with pytest.raises(ValueError, match="variants must be a non-empty subset"):
        VariantsConfig(variants=("ddgan", "xiao"))
    # the benchmark's JSON lines read back into the same rows
    path = tmp_path / "pairs.jsonl"
    base = {"study": "squ9_aamdm_pairs", "config": {"gan_steps": 3}, "hardware": {"cpu": "x"}}
    lines = [{**base, "kind": "seed", **r} for r in rows]
    lines.append({**base, "kind": "summary", "variant": "ddgan"})
    path.write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    back, conf, hw = read_results(path)
    assert back == rows and conf == {"gan_steps": 3} and hw == {"cpu": "x"}
    path.write_text(json.dumps({"study": "other"}) + "\n")
    with pytest.raises(ValueError, match="no squ9_aamdm_pairs seed lines"):
        read_results(path)


@settings(max_examples=60, deadline=None)
@given(
    ma=st.floats(0, 1), sa=st.floats(0, 0.2), mb=st.floats(0, 1), sb=st.floats(0, 0.2),
)  # fmt: skip
def test_describe_says_overlap_exactly_when_the_intervals_overlap(ma, sa, mb, sb):
    row = {m: (0.0, 0.0) for m in METRICS}
    summary = [
        {"variant": "paper", "n_seeds": 3, **row, "precision": (ma, sa)},
        {"variant": "ddgan", "n_seeds": 3, **row, "precision": (mb, sb)},
    ]
    line = next(x for x in describe(summary).splitlines() if x.startswith("precision"))
    numbers, verdict = line.split("; ")
    assert numbers.index("Algorithm 1") < numbers.index("DD-GAN")  # a first, then b
    if abs(ma - mb) <= sa + sb:
        assert "cannot separate" in verdict
    else:
        winner = "Algorithm 1" if ma > mb else "DD-GAN"
        assert verdict.startswith(f"{winner} pairs") and "beyond the seed spread" in verdict
