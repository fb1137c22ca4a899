"""Auto-regressive rollouts: shapes, batching, determinism, decoding and bad input."""

import pytest
import torch

from minimdm.amdm.models import MVAE, DenoiserConfig, MLPDenoiser, MLPRegressor, MVAEConfig
from minimdm.amdm.sampling import NonFiniteFrameError, Sampler, autoregress, rollout
from minimdm.checkpoint import load_checkpoint, save_checkpoint
from minimdm.diffusion import ddim_sample, ddpm_sample
from minimdm.motion.features import Normalizer, StartPose, decode
from minimdm.validate import InputError

J = 2
D = 3 + 12 * J  # the A-MDM frame of a 2-joint skeleton


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture
def amdm_ckpt(tmp_path):
    torch.manual_seed(0)
    model = MLPDenoiser(DenoiserConfig(D, D, width=32, depth=3, time_dim=8))
    norm = Normalizer(torch.randn(D) * 0.1, torch.rand(D) + 0.5)
    meta = {
        "normalizer": norm,
        "diffusion": {"schedule": "cosine", "T": 6, "predicts": "eps"},
        "step": 0,
    }
    save_checkpoint(tmp_path / "m", model, meta)
    return load_checkpoint(tmp_path / "m"), norm


def init_states(C: int = 2) -> torch.Tensor:
    return torch.randn(C, D, generator=torch.Generator().manual_seed(1)) * 0.1


def test_rollout_shapes_and_batching(amdm_ckpt):
    ck, norm = amdm_ckpt
    g = torch.Generator().manual_seed(0)
    r = rollout(ck, init_states(), n_frames=5, n_samples=3, generator=g)
    assert r.features.shape == (2, 3, 5, D)
    assert r.positions.shape == (2, 3, 5, J, 3)
    assert torch.isfinite(r.positions).all()
    assert torch.allclose(r.features, norm.denormalize(r.normalized))
    # samples of one character differ: the model is stochastic
    assert not torch.allclose(r.features[0, 0], r.features[0, 1])
    # the same seed gives the same rollout; a checkpoint path works like a loaded one
    r2 = rollout(ck.paths.weights, init_states(), 5, 3, generator=torch.Generator().manual_seed(0))
    assert torch.equal(r.features, r2.features)
    # positions are the decoded features from the origin
    zero = StartPose(torch.zeros(2, 3, 2), torch.zeros(2, 3))
    assert torch.allclose(r.positions, decode(r.features.double(), zero).float())


def test_rollout_with_fewer_steps_and_a_start_pose(amdm_ckpt):
    ck, _ = amdm_ckpt
    sp = StartPose(torch.tensor([[1.0, 2.0], [0.0, 0.0]]), torch.tensor([0.0, 0.0]))
    a = rollout(ck, init_states(), 4, 2, steps=3, generator=torch.Generator().manual_seed(5))
    b = rollout(
        ck, init_states(), 4, 2, steps=3, generator=torch.Generator().manual_seed(5), start_pose=sp
    )
    assert torch.allclose(b.positions[0] - a.positions[0], torch.tensor([1.0, 2.0, 0.0]), atol=1e-5)
    assert torch.allclose(b.positions[1], a.positions[1])


def test_baselines_roll_out():
    torch.manual_seed(0)
    mse = MLPRegressor(D, D, width=16, depth=3)
    r = rollout(mse, init_states(), 3, n_samples=2)
    assert torch.equal(r.features[:, 0], r.features[:, 1])  # deterministic
    mvae = MVAE(MVAEConfig(D, D, latent_dim=4, width=16, depth=3))
    r = rollout(mvae, init_states(), 3, n_samples=2, generator=torch.Generator().manual_seed(0))
    assert r.features.shape == (2, 2, 3, D)
    assert not torch.equal(r.features[:, 0], r.features[:, 1])


class Exploding(MLPRegressor):
    """Returns NaN for the last sample from its 3rd call on."""

    def __init__(self):
        super().__init__(D, D, width=8, depth=2)
        self.calls = 0

    def forward(self, cond):
        self.calls += 1
        out = super().forward(cond)
        if self.calls >= 3:
            out[-1, 0] = float("nan")
        return out


def test_non_finite_frame_raises_naming_the_frame():
    with pytest.raises(NonFiniteFrameError, match=r"frame 3 .*character 1, sample 1"):
        rollout(Exploding(), init_states(), 10, n_samples=2)


def test_bad_input_is_named(amdm_ckpt):
    ck, _ = amdm_ckpt
    with pytest.raises(ValueError, match=rf"init_states must have shape \(C, {D}\)"):
        rollout(ck, torch.zeros(2, D + 1), 3)
    bad = init_states()
    bad[1, 4] = float("inf")
    with pytest.raises(ValueError, match="character 1 holds NaN/Inf"):
        rollout(ck, bad, 3)
    with pytest.raises(ValueError, match="n_frames must be an integer >= 1"):
        rollout(ck, init_states(), 0)
    with pytest.raises(ValueError, match="steps must lie in"):
        rollout(ck, init_states(), 2, steps=10)


# ------------------------------------------------------------------ the one rollout loop


def _old_sample_frames(model, x0, n_frames, K, normalizer, generator, schedule, steps, eta,
                       predicts, clip_x0):  # fmt: skip
    """The rollout loop as it was before the one loop (a reference copy, kept for the test)."""
    C = x0.shape[0]
    cond = normalizer.normalize(x0) if normalizer is not None else x0
    cond = cond.repeat_interleave(K, dim=0)
    out = torch.empty(C * K, n_frames, cond.shape[1], dtype=torch.float32)
    for f in range(n_frames):
        if isinstance(model, MVAE):
            x = model.sample(cond, generator)
        elif steps is None:
            x = ddpm_sample(model, schedule, tuple(cond.shape), cond=cond, generator=generator,
                            predicts=predicts, clip_x0=clip_x0)  # fmt: skip
        else:
            x = ddim_sample(model, schedule, tuple(cond.shape), cond=cond, steps=steps, eta=eta,
                            generator=generator, predicts=predicts, clip_x0=clip_x0)  # fmt: skip
        out[:, f] = x.float().cpu()
        cond = x
    return out.reshape(C, K, n_frames, -1)


@pytest.mark.parametrize("steps", [None, 3])
def test_rollout_is_bit_identical_to_the_old_loop(amdm_ckpt, steps):
    ck, norm = amdm_ckpt
    g = torch.Generator().manual_seed(4)
    r = rollout(ck, init_states(), 6, 3, steps=steps, generator=g, clip_x0=2.0)
    old = _old_sample_frames(ck.model, init_states(), 6, 3, norm,
                             torch.Generator().manual_seed(4), ck.schedule(), steps, 1.0, "eps",
                             2.0)  # fmt: skip
    assert torch.equal(r.normalized, old)
    mvae = MVAE(MVAEConfig(D, D, latent_dim=4, width=16, depth=3))
    r = rollout(mvae, init_states(), 4, 2, generator=torch.Generator().manual_seed(0))
    old = _old_sample_frames(mvae, init_states(), 4, 2, None, torch.Generator().manual_seed(0),
                             None, None, 1.0, "eps", None)  # fmt: skip
    assert torch.equal(r.normalized, old)


def test_autoregress_feeds_each_frame_back_and_names_frame_and_row():
    seen = []

    def step(f, x):
        seen.append((f, x.clone()))
        return x + f

    out = autoregress(step, torch.zeros(2, 3), 4)
    assert [f for f, _ in seen] == [1, 2, 3, 4]
    assert torch.equal(out[:, :, 0], torch.tensor([[1.0, 3, 6, 10]] * 2))
    assert torch.equal(seen[2][1], out[:, 1])  # the previous frame is the next condition

    def bad(f, x):
        y = x + 1
        if f == 4:
            y[2, 1] = float("inf")
        return y

    with pytest.raises(NonFiniteFrameError, match=r"frame 4 .*for batch row 2") as e:
        autoregress(bad, torch.zeros(3, 2), 6)
    assert (e.value.frame, e.value.row) == (4, 2)
    with pytest.raises(NonFiniteFrameError, match=r"demo produced .* frame 4 .*for row #2"):
        autoregress(bad, torch.zeros(3, 2), 6, who=lambda b: f"row #{b}", desc="demo")
    with pytest.raises(ValueError, match="n_frames must be an integer >= 1"):
        autoregress(bad, torch.zeros(3, 2), 0)


def poison_frame(monkeypatch, k: int, row: int):
    """Make ``Sampler.frame`` return NaN in ``row`` from its k-th call on (frame k)."""
    calls, frame = [], Sampler.frame

    def wrapped(*args, **kwargs):
        x = frame(*args, **kwargs)
        calls.append(1)
        if len(calls) >= k:
            x = x.clone()
            x[row, 0] = float("nan")
        return x

    monkeypatch.setattr(Sampler, "frame", wrapped)


@pytest.mark.parametrize("k", [1, 4])
def test_rollout_names_the_frame_where_the_model_returns_nan(amdm_ckpt, monkeypatch, k):
    ck, _ = amdm_ckpt
    poison_frame(monkeypatch, k, row=3)  # C K = 2 x 2: row 3 = character 1, 1
    with pytest.raises(NonFiniteFrameError, match=rf"frame {k} .*character 1, sample 1") as e:
        rollout(ck, init_states(), 6, 2, generator=torch.Generator().manual_seed(0))
    assert e.value.frame == k


def test_sampler_passes_clip_x0_through_unchanged(tmp_path):
    torch.manual_seed(0)
    model = MLPDenoiser(DenoiserConfig(D, D, width=16, depth=2, time_dim=8, predicts="x0"))
    clip = [[-1.0] * D, [2.0] * D]  # a per-feature range: interpreted by diffusion, not here
    meta = {"diffusion": {"schedule": "cosine", "T": 4, "clip_x0": clip}}
    save_checkpoint(tmp_path / "m", model, meta)
    s = Sampler.load(load_checkpoint(tmp_path / "m"))
    assert s.settings.clip_x0 == clip and s.settings.predicts == "x0"  # from the network
    assert s.schedule.T == 4 and s.normalizer is None and s.layout is None


def test_a_sampler_given_again_refuses_new_settings_and_names_them(amdm_ckpt):
    ck, _ = amdm_ckpt
    sampler = Sampler.load(ck, steps=3)
    assert Sampler.load(sampler) is sampler
    with pytest.raises(InputError, match=r"Sampler.*steps, eta cannot be given again"):
        rollout(sampler, init_states(), 2, steps=2, eta=0.0)
    with pytest.raises(InputError, match=r"clip_x0"):
        Sampler.load(sampler, clip_x0=None)
