"""A condition of several previous frames (``TrainConfig.history``): the training windows, the
rolling condition of scheduled sampling and of the rollout, and the delta's origin."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as hst
from torch import Tensor

from minimdm.amdm.losses import make_windows, window_loss
from minimdm.amdm.models import DenoiserConfig, MLPDenoiser, MLPRegressor
from minimdm.amdm.sampling import Sampler, rollout
from minimdm.amdm.train import train_amdm
from minimdm.amdm.train_config import TrainConfig, build_network
from minimdm.checkpoint import load_checkpoint
from minimdm.validate import InputError

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py
D = 6


class Oldest(MLPRegressor):
    """A regressor whose next frame is the oldest frame of its condition: x_f = x_{f-H}. A
    rollout of it repeats the H start frames in their order, and a wrong order shows."""

    def forward(self, cond: Tensor) -> Tensor:
        return cond[:, : self.x_dim] + 0.0 * self.net[0].weight.sum()


@given(history=hst.integers(1, 5), n_frames=hst.integers(1, 12))
@settings(max_examples=25, deadline=None)
def test_a_rollout_feeds_the_last_h_frames_oldest_first(history, n_frames):
    model = Oldest(D, history * D, width=8, depth=2)
    start = torch.randn(2, history, D)
    init = start[:, 0] if history == 1 else start
    out = rollout(model, init, n_frames, n_samples=3, decode_positions=False).features
    assert out.shape == (2, 3, n_frames, D)
    for f in range(n_frames):  # x_{f+1} = x_{f+1-H}: the start frames, over and over
        torch.testing.assert_close(out[:, :, f], start[:, None, f % history].expand(2, 3, D))


def test_a_history_model_refuses_a_single_start_frame_and_names_the_shape():
    model = Oldest(D, 3 * D, width=8, depth=2)
    with pytest.raises(InputError, match=r"\(C, 3, 6\) or \(3, 6\) for a history of 3"):
        rollout(model, torch.zeros(2, D), 4)
    with pytest.raises(InputError, match="history of 3"):
        rollout(model, torch.zeros(2, 2, D), 4)


@given(history=hst.integers(1, 4), n_r=hst.integers(1, 4), p=hst.sampled_from([0.0, 1.0]))
@settings(max_examples=20, deadline=None)
def test_scheduled_sampling_rolls_the_condition_like_the_rollout(history, n_r, p):
    """Teacher forcing conditions frame f on its H recorded predecessors; student forcing on the
    model's own frames as they come, the recorded ones before them: for the Oldest model, the
    student's loss is what a rollout from the window's first H frames gives."""
    torch.manual_seed(0)
    model = Oldest(D, history * D, width=8, depth=2)
    windows = torch.randn(5, history + n_r, D)
    loss, info = window_loss(model, windows, p, torch.Generator(), kind="mse", history=history)
    if p == 0:
        expect = torch.stack(
            [(windows[:, f - history] - windows[:, f]) ** 2 for f in range(history, history + n_r)]
        ).mean()
    else:
        start = windows[:, 0] if history == 1 else windows[:, :history]
        fed = rollout(model, start, n_r, decode_positions=False).features[:, 0]
        expect = ((fed - windows[:, history:]) ** 2).mean()
        assert info["student_frac"] == (1.0 if n_r > 1 else 0.0)
    torch.testing.assert_close(loss, expect)


def test_windows_too_short_for_the_history_are_refused():
    model = Oldest(D, 3 * D, width=8, depth=2)
    with pytest.raises(ValueError, match=r"\(B, 2 \+ N_r \+ 1 >= 4, D\) for a history of 3"):
        window_loss(model, torch.zeros(4, 3, D), 0.0, None, kind="mse", history=3)


def test_a_history_denoiser_measures_its_change_from_the_last_frame():
    k = torch.rand(D) + 0.5
    cfg = DenoiserConfig(D, 3 * D, 16, 2, 8, "x0", delta_scale=k.tolist(), history=3)
    net, one = (
        MLPDenoiser(cfg),
        MLPDenoiser(DenoiserConfig(D, D, 16, 2, 8, "x0", delta_scale=k.tolist())),
    )
    cond, x = torch.randn(4, 3 * D), torch.randn(4, D)
    z = net.to_delta(x, cond)
    torch.testing.assert_close(z, one.to_delta(x, cond[:, -D:]))
    torch.testing.assert_close(net.from_delta(z, cond), x)
    with pytest.raises(ValueError, match=r"history of 3 frames needs cond_dim = 3 \* 6, got 6"):
        MLPDenoiser(DenoiserConfig(D, D, 16, 2, 8, history=3))


def test_a_history_model_trains_resumes_and_samples_from_its_checkpoint(tmp_path):
    """Training windows hold H - 1 more frames; the checkpoint restores the history, and its
    sampler rolls out from H start frames."""
    torch.manual_seed(0)
    t = torch.arange(80.0)[:, None]
    clips = [torch.sin(t * (0.1 + 0.05 * i) + torch.arange(D)) for i in range(2)]
    cfg = TrainConfig(
        width=16, depth=2, time_dim=8, T=4, batch_size=8, total_steps=4, rollout=2, history=3,
        teacher_steps=1, ramp_steps=1, eval_interval=4, ckpt_interval=0, eval_windows=8,
        delta=True, cond_noise=0.5,
    )  # fmt: skip
    result = train_amdm(cfg, tmp_path, clips, progress=False)
    assert result.steps == 4 and all(
        torch.isfinite(torch.tensor(h["loss"])) for h in result.history if "loss" in h
    )
    ckpt = load_checkpoint(tmp_path)
    assert ckpt.model.config.history == 3 and ckpt.model.config.cond_dim == 3 * D
    assert ckpt.metadata["data"]["windows"] == len(make_windows(clips, 4))  # N_r + H - 1 = 4
    sampler = Sampler.load(ckpt)
    assert sampler.history == 3
    out = rollout(ckpt, clips[0][10:13], 5, 2, generator=torch.Generator().manual_seed(0),
                  decode_positions=False)  # fmt: skip
    assert out.features.shape == (1, 2, 5, D) and torch.isfinite(out.features).all()


def test_history_must_be_a_count():
    with pytest.raises(ValueError, match="history must be >= 1"):
        TrainConfig(history=0)
    net = build_network(TrainConfig(model_kind="mvae", history=2, width=8, depth=2), D)
    assert net.config.cond_dim == 2 * D


def test_an_initial_state_gives_a_history_model_the_frames_before_it():
    """Table 1 starts a history model from x_0 and the H - 1 recorded frames before it; a
    state nearer the take's start than that repeats the take's first frame."""
    from minimdm.amdm.evaluation import _state, random_states
    from minimdm.motion.corpora import load_motion
    from minimdm.motion.features import encode

    clip = load_motion("bandai-namco-1", names=["dataset-1_walk_normal_002"])[0]
    feats = encode(clip)
    late, early = _state(clip, feats, 20, 0), _state(clip, feats, 2, 0)
    torch.testing.assert_close(late.condition(1), feats[19])
    torch.testing.assert_close(late.condition(4), feats[16:20])
    torch.testing.assert_close(early.condition(4), feats[[0, 0, 0, 1]])
    (state,) = random_states([clip], 1, 10, seed=3)
    torch.testing.assert_close(state.condition(5)[-1], state.features)


def test_one_frame_fed_to_a_history_model_is_refused_with_the_reason():
    """Inpainting, beam search and steering feed the sampler one frame; a history model says
    what it needs instead of failing inside the network."""
    net = MLPDenoiser(DenoiserConfig(D, 3 * D, 16, 2, 8, history=3))
    from minimdm.diffusion import NoiseSchedule

    sampler = Sampler.load(net, schedule=NoiseSchedule("cosine", 4))
    with pytest.raises(InputError, match=r"conditions on the 3 frames before x_f: .*\(B, 18\)"):
        sampler.frame(torch.zeros(2, D))
    assert sampler.frame(torch.zeros(2, 3 * D), torch.Generator()).shape == (2, D)


class Seen(MLPDenoiser):
    """A denoiser that records the condition it is given."""

    def forward(self, x_t, t, cond=None):
        self.seen = cond.clone()
        return super().forward(x_t, t, cond)


@pytest.mark.parametrize("how", ["each", "shared"])
def test_shared_condition_noise_offsets_the_whole_past_alike(how):
    """'shared' noise moves the H frames of a condition by one draw, so the changes between
    them stay the recorded ones; 'each' noises every frame on its own."""
    from minimdm.amdm.losses import frame_loss
    from minimdm.diffusion import NoiseSchedule

    net = Seen(DenoiserConfig(D, 3 * D, 16, 2, 8, "x0", history=3))
    cond, x = torch.randn(64, 3 * D), torch.randn(64, D)
    schedule = NoiseSchedule("cosine", 4)
    g = torch.Generator().manual_seed(0)
    frame_loss(net, x, cond, g, schedule=schedule, cond_noise=0.5, cond_noise_history=how)
    noise = (net.seen - cond).unflatten(1, (3, D))  # (B, H, D)
    assert noise.std() == pytest.approx(0.5, rel=0.15)
    same = all(torch.allclose(noise[:, 0], noise[:, i], atol=1e-5) for i in (1, 2))
    assert same == (how == "shared")
    with pytest.raises(ValueError, match="cond_noise_history must be 'each' or 'shared'"):
        TrainConfig(cond_noise_history="both")
