"""Auto-regressive rollouts: shapes, batching, determinism, decoding and bad input."""

import pytest
import torch

from minimdm.amdm.models import MVAE, DenoiserConfig, MLPDenoiser, MLPRegressor, MVAEConfig
from minimdm.amdm.sampling import NonFiniteFrameError, rollout
from minimdm.checkpoint import load_checkpoint, save_checkpoint
from minimdm.motion.features import Normalizer, StartPose, decode

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
