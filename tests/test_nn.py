"""The shared pieces of minimdm.nn: the MLP body, the EMA of weights, the learning-rate schedule.

(That every shipped checkpoint still loads strictly is tests/test_clip_range.py; that its
networks compute what they computed before, the chapters' checked outputs.)
"""

import copy

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from minimdm.amdm.train_config import TrainConfig, learning_rate
from minimdm.nn import ACTIVATIONS, MLP, cosine_lr, ema_update, optimizer_step, set_lr

pytestmark = pytest.mark.usefixtures("one_thread")


def _reference(m: MLP, x, add=None, concat=None, act=F.silu):
    """The block written out: Linear (+ add) -> activation -> LayerNorm, then the output layer."""
    h = x
    for i, layer in enumerate([m.input, *m.hidden]):
        h = layer(h if concat is None else torch.cat([h, concat], -1))
        h = act(h + (0 if add is None else add))
        if m.norm:
            h = F.layer_norm(h, h.shape[-1:], m.norms[i].weight, m.norms[i].bias)
    return m.output(h if concat is None else torch.cat([h, concat], -1))


def _perturbed(m: nn.Module) -> nn.Module:
    with torch.no_grad():  # LayerNorms start at 1 and 0: make them count
        for p in m.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return m


@settings(max_examples=25, deadline=None)
@given(
    in_dim=st.integers(1, 5),
    out_dim=st.integers(1, 4),
    width=st.integers(2, 8),
    depth=st.integers(2, 5),
    activation=st.sampled_from(sorted(ACTIVATIONS)),
    norm=st.booleans(),
    seed=st.integers(0, 100),
)
def test_mlp_is_linear_activation_layernorm_blocks(
    in_dim, out_dim, width, depth, activation, norm, seed
):
    torch.manual_seed(seed)
    m = _perturbed(MLP(in_dim, out_dim, width, depth, activation, norm))
    act = {"silu": F.silu, "mish": F.mish, "leaky_relu": lambda h: F.leaky_relu(h, 0.2)}[activation]
    x, add = torch.randn(3, in_dim), torch.randn(3, width)
    with torch.no_grad():
        torch.testing.assert_close(m(x), _reference(m, x, act=act))
        torch.testing.assert_close(m(x, add=add), _reference(m, x, add=add, act=act))
        # the same layers as an nn.Sequential compute the same function
        torch.testing.assert_close(m.sequential()(x), m(x), rtol=0, atol=0)
    assert len([p for p in m.parameters()]) == 2 * depth + (2 * (depth - 1) if norm else 0)


def test_mlp_concat_reaches_every_layer():
    torch.manual_seed(0)
    m = _perturbed(MLP(3, 2, 8, 4, concat_dim=2))
    assert m.input.in_features == 5 and m.output.in_features == 10
    assert all(layer.in_features == 10 for layer in m.hidden)
    x, z = torch.randn(4, 3), torch.randn(4, 2)
    with torch.no_grad():
        torch.testing.assert_close(m(x, concat=z), _reference(m, x, concat=z))
    with torch.no_grad():  # z reaches the output layer directly, not only through h
        m.output.weight[:, 8:] += 1.0
        torch.testing.assert_close(m(x, concat=z), _reference(m, x, concat=z))
    with pytest.raises(ValueError, match="concat must be given exactly when concat_dim > 0"):
        m(x)
    with pytest.raises(ValueError, match="concat must be given"):
        MLP(3, 2, 8, 3)(x, concat=z)
    with pytest.raises(ValueError, match="cannot run as an nn.Sequential"):
        m.sequential()


def test_mlp_activation_matters_and_bad_arguments_are_named():
    torch.manual_seed(0)
    silu = MLP(3, 2, 8, 3)
    mish = MLP(3, 2, 8, 3, activation="mish")
    mish.load_state_dict(silu.state_dict())  # same weights, same keys
    x = torch.randn(5, 3)
    assert not torch.allclose(silu(x), mish(x))
    assert isinstance(mish.act, nn.Mish) and isinstance(silu.act, nn.SiLU)
    with pytest.raises(ValueError, match="activation must be one of"):
        MLP(3, 2, 8, 3, activation="relu6")
    with pytest.raises(ValueError, match="depth must be >= 2"):
        MLP(3, 2, 8, 1)


def test_mlp_state_dict_names_and_sequential_shares_the_parameters():
    m = MLP(3, 2, 8, 3)
    assert set(m.state_dict()) == {
        f"{n}.{p}"
        for n in ("input", "hidden.0", "norms.0", "norms.1", "output")
        for p in ("weight", "bias")
    }
    seq = m.sequential()
    assert set(seq.state_dict()) == {
        f"{i}.{p}" for i in (0, 2, 3, 5, 6) for p in ("weight", "bias")
    }
    no_norm = MLP(3, 2, 8, 3, norm=False)
    assert set(no_norm.sequential().state_dict()) == {
        f"{i}.{p}" for i in (0, 2, 4) for p in ("weight", "bias")
    }
    assert not any(k.startswith("norms") for k in no_norm.state_dict())
    with torch.no_grad():
        seq[0].weight.add_(1.0)
    assert torch.equal(seq[0].weight, m.input.weight)


# ---- EMA ------------------------------------------------------------------------------------


def _net() -> nn.Module:
    return nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))


def test_ema_update_follows_the_warm_up_formula_and_copies_buffers():
    torch.manual_seed(0)
    model, average = _net(), _net()
    before = copy.deepcopy(average.state_dict())
    model[1].running_mean.fill_(3.0)
    for step, want_d in ((0, 1 / 10), (5, 6 / 15), (10_000, 0.99)):
        avg = copy.deepcopy(average)
        d = ema_update(avg, model, 0.99, step)
        assert d == pytest.approx(want_d)
        for name, p in model.named_parameters():
            want = d * before[name] + (1 - d) * p.detach()
            torch.testing.assert_close(avg.state_dict()[name], want)
        assert torch.equal(avg[1].running_mean, model[1].running_mean)  # buffers: copied


def test_ema_update_on_a_state_dict_equals_on_a_module():
    torch.manual_seed(0)
    model, average = _net(), _net()
    sd = {k: v.clone() for k, v in average.state_dict().items()}
    for step in range(4):
        with torch.no_grad():
            model[0].weight.add_(0.1)
        ema_update(average, model, 0.9, step)
        ema_update(sd, model, 0.9, step)
    for k, v in average.state_dict().items():
        assert torch.equal(sd[k], v)


@settings(max_examples=20, deadline=None)
@given(decay=st.floats(0.0, 0.999), steps=st.integers(1, 30))
def test_ema_of_fixed_weights_closes_the_gap_geometrically(decay, steps):
    model, average = nn.Linear(2, 2), nn.Linear(2, 2)
    with torch.no_grad():
        model.weight.fill_(1.0)
        average.weight.fill_(0.0)
    gap = 1.0
    for step in range(steps):
        gap *= ema_update(average, model, decay, step)
    torch.testing.assert_close(average.weight, torch.full((2, 2), 1.0 - gap))


def test_ema_rejects_a_bad_decay_and_a_missing_entry():
    with pytest.raises(ValueError, match=r"decay must lie in \[0, 1\)"):
        ema_update(nn.Linear(2, 2), nn.Linear(2, 2), 1.0, 0)
    with pytest.raises(ValueError, match="the average has no entry 'bias'"):
        ema_update({"weight": torch.zeros(2, 2)}, nn.Linear(2, 2), 0.9, 0)


# ---- the learning-rate schedule ---------------------------------------------------------------


@settings(max_examples=50, deadline=None)
@given(
    total=st.integers(1, 300),
    warmup=st.integers(0, 50),
    lr=st.floats(1e-5, 1.0),
    ratio=st.floats(0.0, 1.0),
)
def test_cosine_lr_warms_up_then_decays_to_lr_min(total, warmup, lr, ratio):
    lr_min = lr * ratio
    rates = [cosine_lr(s, total, lr, lr_min, warmup) for s in range(total + warmup + 5)]
    for s in range(min(warmup, len(rates))):
        assert rates[s] == pytest.approx(lr * (s + 1) / warmup)
    after = rates[warmup:]
    assert after[0] == pytest.approx(lr)
    assert all(b <= a + 1e-12 for a, b in zip(after, after[1:], strict=False))  # never rises
    if total - warmup >= 2:  # the decay reaches lr_min at the last step and stays there
        assert rates[total - 1] == pytest.approx(lr_min, abs=1e-12)
    assert rates[-1] == pytest.approx(lr_min, abs=1e-12)
    assert all(lr_min - 1e-12 <= r <= lr + 1e-12 for r in after)
    assert all(0 <= r <= lr + 1e-12 for r in rates)


def test_cosine_lr_is_the_trainers_schedule_and_rejects_bad_lengths():
    cfg = TrainConfig(lr=1e-3, lr_min=1e-4, total_steps=50)
    for step in (0, 1, 24, 49, 60):
        assert learning_rate(cfg, step) == cosine_lr(step, 50, 1e-3, 1e-4)
    assert cosine_lr(25, 51, 2.0, 0.0) == pytest.approx(1.0)  # half-way: the mean
    with pytest.raises(ValueError, match="total_steps must be >= 1"):
        cosine_lr(0, 0, 1.0)
    opt = torch.optim.Adam(
        [{"params": [nn.Parameter(torch.zeros(1))]}, {"params": [nn.Parameter(torch.zeros(1))]}]
    )
    set_lr(opt, 0.123)
    assert [g["lr"] for g in opt.param_groups] == [0.123, 0.123]


def test_optimizer_step_is_zero_backward_clip_step():
    torch.manual_seed(0)
    a, b = nn.Linear(3, 3), nn.Linear(3, 1)
    x = torch.randn(8, 3)
    ref = copy.deepcopy(a)
    opt_ref = torch.optim.SGD(ref.parameters(), lr=0.1)
    opt = torch.optim.SGD(a.parameters(), lr=0.1)
    for _ in range(3):  # written out: zero, backward, clip to norm 0.01, step
        loss_ref = (b(ref(x)) ** 2).mean()
        opt_ref.zero_grad(set_to_none=True)
        loss_ref.backward()
        nn.utils.clip_grad_norm_(ref.parameters(), 0.01)
        opt_ref.step()
        b.zero_grad(set_to_none=True)
        optimizer_step(opt, (b(a(x)) ** 2).mean(), list(a.parameters()), grad_clip=0.01)
    for p, q in zip(a.parameters(), ref.parameters(), strict=True):
        assert torch.equal(p, q)
    assert b.weight.grad is not None  # a plain backward reaches every parameter of the graph
    b.zero_grad(set_to_none=True)
    optimizer_step(opt, (b(a(x)) ** 2).mean(), list(a.parameters()), only_these=True)
    assert b.weight.grad is None  # a generator's step leaves the discriminator alone
