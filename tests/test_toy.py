"""Tests for minimdm.toy.squ9: the Squ-9 rule, its metrics, plots and trainers."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
import torch

from minimdm.amdm.models import DenoiserConfig, MLPDenoiser, MLPRegressor
from minimdm.diffusion import NoiseSchedule
from minimdm.toy.squ9 import (
    Squ9,
    plot_transition_matrix,
    plot_transitions,
    squ9_metrics,
    train_denoiser,
    train_regressor,
)


def test_mode_centers_grid():
    sq = Squ9(spacing=2.0)
    c = sq.mode_centers
    assert c.shape == (9, 2)
    assert set(c[:, 0].tolist()) == {-2.0, 0.0, 2.0} == set(c[:, 1].tolist())
    torch.testing.assert_close(c[4], torch.zeros(2))  # mode 4 is the centre
    assert (sq.mode_of(c) == torch.arange(9)).all()


def test_pairs_follow_rule_other():
    sq = Squ9()
    g = torch.Generator().manual_seed(0)
    x_prev, x_next = sq.sample_pairs(18_000, g)
    assert x_prev.shape == x_next.shape == (18_000, 2)
    a, b = sq.mode_of(x_prev), sq.mode_of(x_next)
    assert (a != b).all(), "the next point never stays in its mode"
    counts = torch.zeros(9, 9)
    counts.index_put_((a, b), torch.ones(len(a)), accumulate=True)
    allowed = ~torch.eye(9, dtype=torch.bool)
    assert (counts[allowed] > 0).all(), "every source reaches all 8 other modes"
    # uniform over the 8 others: 250 expected per cell, a 5-sigma band
    assert (counts[allowed] - 250).abs().max() < 5 * 250**0.5
    # points scatter around their centre with the configured sigma
    resid = x_next - sq.mode_centers[b]
    assert abs(resid.std().item() - sq.sigma) < 0.005


def test_neighbors_rule_and_matrix():
    sq = Squ9(rule="neighbors")
    P = sq.transition_matrix()
    torch.testing.assert_close(P.sum(1), torch.ones(9))
    assert (P > 0).sum(1).tolist() == [2, 3, 2, 3, 4, 3, 2, 3, 2]
    x_prev, x_next = sq.sample_pairs(2000, torch.Generator().manual_seed(1))
    assert P[sq.mode_of(x_prev), sq.mode_of(x_next)].min() > 0
    torch.testing.assert_close(Squ9().transition_matrix().sum(1), torch.ones(9))


def test_sequence_follows_rule_and_is_seeded():
    sq = Squ9()
    seq = sq.sample_sequence(50, n=40, generator=torch.Generator().manual_seed(2))
    assert seq.shape == (40, 50, 2)
    m = sq.mode_of(seq)
    assert (m[:, 1:] != m[:, :-1]).all()
    again = sq.sample_sequence(50, n=40, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(seq, again, rtol=0, atol=0)
    assert len(torch.unique(m)) == 9


def test_metrics_on_ground_truth():
    sq = Squ9()
    x_prev, x_next = sq.sample_pairs(20_000, torch.Generator().manual_seed(3))
    m = squ9_metrics(x_prev, x_next, sq)
    assert m["coverage"] == 1.0
    assert (m["coverage_per_mode"] == 1).all()
    # the 2D Gaussian mass inside radius 3 sigma is 1 - exp(-9/2) = 0.9889
    assert abs(m["precision"] - (1 - np.exp(-4.5))) < 0.005
    assert m["transition_tv"] < 0.05  # sampling noise only (~2200 samples per row)
    assert m["matrix"].shape == (9, 9)
    np.testing.assert_allclose(m["matrix"].sum(1), 1, rtol=1e-5)
    assert m["counts"].sum() == 20_000


def test_metrics_on_collapsed_predictor():
    """A predictor that returns the conditional mean collapses onto the centre mode.

    The mean of the 8 other centres is -c/8, within 3 sigma of the centre: the centre is an
    allowed target of the 8 outer modes, so precision is 8/9 (precision alone is fooled), but
    coverage is 1/9 and the transition matrix is far from the truth.
    """
    sq = Squ9()
    x_prev, _ = sq.sample_pairs(9000, torch.Generator().manual_seed(4))
    src = sq.mode_of(x_prev)
    mean_pred = -sq.mode_centers[src] / 8
    m = squ9_metrics(x_prev, mean_pred, sq)
    assert m["coverage"] == pytest.approx(1 / 9)
    assert m["precision"] == pytest.approx((src != 4).float().mean().item())
    assert m["transition_tv"] == pytest.approx(8 / 9, abs=1e-5)
    # a blurred predictor half-way between modes is never precise and covers nothing
    m = squ9_metrics(x_prev, torch.full_like(x_prev, 0.5), sq)
    assert m["precision"] == 0 and m["coverage"] == 0
    # one mode only (the right one of 8): coverage 1/8 for every source
    target = sq.mode_centers[(src + 1) % 9]
    m = squ9_metrics(x_prev, target, sq)
    assert m["precision"] == 1.0
    np.testing.assert_allclose(m["coverage_per_mode"], 1 / 8)


def test_metrics_bad_input():
    with pytest.raises(ValueError, match="x_prev"):
        squ9_metrics(torch.zeros(5, 2), torch.zeros(4, 2))
    bad = torch.zeros(4, 2)
    bad[1, 0] = float("nan")
    with pytest.raises(ValueError, match="x_next"):
        squ9_metrics(torch.zeros(4, 2), bad)
    with pytest.raises(ValueError, match="sigma"):
        Squ9(sigma=0)
    with pytest.raises(ValueError, match="rule"):
        Squ9(rule="diagonal")
    with pytest.raises(ValueError, match="length"):
        Squ9().sample_sequence(0)


def test_plots_return_figures():
    sq = Squ9()
    x_prev, x_next = sq.sample_pairs(200, torch.Generator().manual_seed(5))
    fig = plot_transitions(x_prev, x_next, arrows=20, title="truth")
    assert isinstance(fig, matplotlib.figure.Figure)
    fig2 = plot_transition_matrix(squ9_metrics(x_prev, x_next)["matrix"])
    assert isinstance(fig2, matplotlib.figure.Figure)
    import matplotlib.pyplot as plt

    plt.close("all")


def test_trainers_reduce_loss_and_are_seeded():
    sq = Squ9()
    x_prev, x_next = sq.sample_pairs(2000, torch.Generator().manual_seed(6))

    def fit(seed):
        torch.manual_seed(seed)
        model = MLPDenoiser(DenoiserConfig(2, 2, width=32, depth=3, time_dim=16))
        g = torch.Generator().manual_seed(seed)
        h = train_denoiser(model, NoiseSchedule("cosine", 10), x_prev, x_next, 150, 128, 3e-3, g)
        return h, model

    h1, m1 = fit(0)
    h2, m2 = fit(0)
    assert len(h1) == 150 and h1 == h2
    assert not m1.training
    assert sum(h1[-20:]) < sum(h1[:20])
    torch.manual_seed(0)
    reg = MLPRegressor(2, 2, width=32, depth=3)
    h = train_regressor(reg, x_prev, x_next, 300, 256, 3e-3, torch.Generator().manual_seed(0))
    # the best one-to-one map is the conditional mean -c/8; its MSE is the data's spread
    pred = reg(x_prev).detach()
    expected = -sq.mode_centers[sq.mode_of(x_prev)] / 8
    assert (pred - expected).norm(dim=-1).mean() < 0.1
    assert h[-1] < h[0]


def test_posterior_x0_is_the_ideal_denoiser():
    """The closed form beats any other estimate on the x0 loss and matches a Monte-Carlo mean."""
    from minimdm.diffusion import NoiseSchedule, q_sample

    sq = Squ9()
    s = NoiseSchedule("cosine", 20)
    g = torch.Generator().manual_seed(0)
    x_prev, x_next = sq.sample_pairs(20_000, g)
    for t in (0, 10, 19):
        x_t = q_sample(s, x_next, t, generator=g)
        ideal = sq.posterior_x0(x_t, x_prev, s.alphas_cumprod[t])
        err = ((ideal - x_next) ** 2).sum(-1).mean()
        for other in (x_t, torch.zeros_like(x_t), ideal + 0.05):
            assert err < ((other - x_next) ** 2).sum(-1).mean()
    # at the noisiest level the answer is the mean of the 8 allowed targets, -c_k / 8
    src = sq.mode_of(x_prev)
    x_t = torch.randn(x_prev.shape, generator=g)
    ideal = sq.posterior_x0(x_t, x_prev, 1e-8)
    torch.testing.assert_close(ideal, -sq.mode_centers[src] / 8, atol=1e-3, rtol=0)


def test_parameterisation_study_rows():
    """The eps/x0/v study of chapter 1: one row per parameterisation, the ideal denoiser's error
    is the floor of every model's, and the ideal ignores its input at the noisiest level."""
    from minimdm.studies.squ9_parameterisation import (
        input_gain_by_level,
        run_seed,
        summarize,
        to_json,
    )

    rows = run_seed(0, T=5, train=dict(steps=30, batch_size=256, lr=3e-3))
    assert [r["predicts"] for r in rows] == ["eps", "x0", "v"]
    for r in rows:
        assert len(r["x0_err"]) == len(r["ideal_err"]) == len(r["input_gain"]) == 5
        assert all(m >= i - 1e-3 for m, i in zip(r["x0_err"], r["ideal_err"], strict=True))
        assert "model" not in to_json(r)
    summary = summarize(rows + [{**r, "seed": 1} for r in rows])
    assert summary[0]["n_seeds"] == 2 and summary[0]["coverage"][1] == 0
    ideal = input_gain_by_level(None, NoiseSchedule("cosine", 20), Squ9(), n=500)
    assert abs(ideal[-1]) < 0.01 and ideal[0] > 0.3
