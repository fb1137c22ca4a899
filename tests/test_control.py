"""Control without retraining: hooks on the sampler loop, beam search, inpainting, inbetweening.

Unit tests use untrained tiny networks; the behaviour tests (reaching a target, landing on a
keyframe) use a tiny A-MDM trained for a few seconds on four walking/running clips.
"""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from minimdm import control as C
from minimdm.amdm.models import MVAE, DenoiserConfig, MLPDenoiser, MLPRegressor, MVAEConfig
from minimdm.amdm.sampling import Sampler, rollout
from minimdm.checkpoint import load_checkpoint, save_checkpoint
from minimdm.diffusion import NoiseSchedule, ddpm_sample, q_sample
from minimdm.motion.features import FeatureLayout, Normalizer, decode_root
from minimdm.motion.skeleton import Skeleton
from minimdm.utils import num_threads

J = 2
D = 3 + 12 * J  # the A-MDM frame of a 2-joint skeleton
LAYOUT = FeatureLayout(("root", "head"))


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


DELTA = (0.2 + torch.rand(D, generator=torch.Generator().manual_seed(5))).tolist()
"""A delta model's k: the chain denoises (x_f - x_{f-1}) / k (TrainConfig.delta)."""


class Recorder(MLPDenoiser):
    """A tiny denoiser that records every call: (level t, input x_t)."""

    def __init__(self, predicts: str = "eps", delta: bool = False) -> None:
        k = DELTA if delta else None
        cfg = DenoiserConfig(D, D, width=16, depth=3, time_dim=8, predicts=predicts, delta_scale=k)
        super().__init__(cfg)
        self.calls: list[tuple[int, torch.Tensor]] = []

    def forward(self, x_t, t, cond=None):
        self.calls.append((int(t[0]), x_t.clone()))
        return super().forward(x_t, t, cond)


def tiny_ckpt(tmp_path, predicts="eps", T=6, delta=False):
    torch.manual_seed(0)
    k = DELTA if delta else None
    cfg = DenoiserConfig(D, D, width=32, depth=3, time_dim=8, predicts=predicts, delta_scale=k)
    model = MLPDenoiser(cfg)
    norm = Normalizer(torch.randn(D) * 0.1, torch.rand(D) + 0.5)
    meta = {
        "normalizer": norm,
        "diffusion": {"schedule": "cosine", "T": T, "predicts": predicts, "clip_x0": 5.0},
        "feature_layout": LAYOUT,
    }
    save_checkpoint(tmp_path / "m", model, meta)
    return load_checkpoint(tmp_path / "m")


def start_state(B=None):
    g = torch.Generator().manual_seed(1)
    return torch.randn(*((B,) if B else ()), D, generator=g) * 0.1


# ------------------------------------------------------------------ hooks on the sampler loop


def test_inpaint_hook_is_applied_after_every_step_at_the_right_level():
    schedule = NoiseSchedule("cosine", 5)
    net = Recorder()
    B = 3
    target = torch.randn(B, D)
    mask = torch.zeros(D, dtype=torch.bool)
    mask[[0, 2, 7]] = True
    t_stop = 1
    hook = C.inpaint_hook(schedule, target, mask, torch.Generator().manual_seed(7), t_stop)
    seen = []

    def spy(t, x_t, x0_hat):
        out = hook(t, x_t, x0_hat)
        seen.append((t, x_t.clone(), out.clone()))
        return out

    cond = torch.randn(B, D)
    x = ddpm_sample(
        net, schedule, (B, D), cond=cond, generator=torch.Generator().manual_seed(0), hook=spy
    )
    assert [t for t, _, _ in seen] == [3, 2, 1, 0, -1]  # after each of the 5 steps
    replay = torch.Generator().manual_seed(7)  # the hook's own noise, replayed
    for t, before, after in seen:
        assert torch.equal(after[:, ~mask], before[:, ~mask])  # unmasked: untouched
        if t >= t_stop:  # eq. 4: masked entries = the target noised to level t
            expected = q_sample(schedule, target, t, generator=replay)
            assert torch.allclose(after[:, mask], expected[:, mask])
        else:  # inpainting stopped early: nothing replaced
            assert torch.equal(after, before)
    # the model's next input is the hook's output
    for (_, _, after), (_, x_next) in zip(seen[:-1], net.calls[1:], strict=True):
        assert torch.equal(after, x_next)
    assert torch.equal(x, seen[-1][2])


def test_inpaint_hook_at_the_last_level_pastes_the_target():
    schedule = NoiseSchedule("cosine", 4)
    target = torch.randn(2, D)
    hook = C.inpaint_hook(schedule, target, torch.ones(D, dtype=torch.bool))
    assert torch.equal(hook(-1, torch.randn(2, D), torch.zeros(2, D)), target)


def test_inbetween_t_start_follows_eq5():
    T = 20
    for n in (1, 5, 20, 60):
        ts = [C.inbetween_t_start(f, n, T) for f in range(1, n + 1)]
        assert ts[-1] == 0  # the keyframe's frame runs one, the least noisy, step
        assert all(a >= b for a, b in zip(ts, ts[1:], strict=False))  # fewer steps near it
        for f, t in zip(range(1, n + 1), ts, strict=True):
            assert t == max(math.ceil((1 - f / n) * T) - 1, 0)  # t0 = (1 - f/N) t_max
    assert C.inbetween_t_start(1, 100, T) == T - 1  # a long transition starts from noise
    with pytest.raises(ValueError, match=r"f must lie in \[1, n=5\]"):
        C.inbetween_t_start(6, 5, T)


@pytest.mark.parametrize("delta", [False, True])
def test_inbetween_starts_each_chain_from_the_noised_keyframe(tmp_path, delta):
    """A delta model's chain starts from the keyframe's change from the previous frame."""
    ck = tiny_ckpt(tmp_path, T=8)
    net = Recorder(delta=delta)
    cm = Sampler.load(net, schedule=ck.schedule(), normalizer=Normalizer.from_dict(ck.normalizer))
    key = torch.randn(D) * 0.1
    N = 6
    m = C.inbetween(cm, start_state(), key, N + 2, torch.Generator().manual_seed(0), at=N)
    firsts = [i for i, (t, _) in enumerate(net.calls) if i == 0 or t >= net.calls[i - 1][0]]
    starts = [net.calls[i][0] for i in firsts]
    assert starts == [C.inbetween_t_start(f, N, 8) for f in range(1, N + 1)] + [7, 7]
    assert m.info["t_start"] == starts[:N] + [-1, -1]
    # a chain's first input is the normalized keyframe, as the chain sees it, noised to its level
    key_n = cm.normalize(key)
    conds = torch.cat([cm.normalize(start_state())[None], m.normalized[: N - 1]])  # (N, D)
    for i, t, cond in zip(firsts[:N], starts[:N], conds, strict=True):
        x = net.calls[i][1][0]
        key_t = cm.chain_target(key_n[None], cond[None])[0]
        scale = NoiseSchedule("cosine", 8).sqrt_one_minus_alphas_cumprod[t]
        assert (x - NoiseSchedule("cosine", 8).sqrt_alphas_cumprod[t] * key_t).std() < 1.5 * scale
    assert m.features.shape == (N + 2, D)


# ------------------------------------------------------------------ inpainting


@pytest.mark.parametrize("delta", [False, True])
def test_fully_masked_inpainting_reproduces_the_target_exactly(tmp_path, delta):
    """Also for a delta model, whose chain denoises each target's change from its frame's
    condition."""
    ck = tiny_ckpt(tmp_path, delta=delta)
    F = 7
    targets = torch.randn(F, D, generator=torch.Generator().manual_seed(3))
    m = C.inpaint(ck, start_state(), targets, torch.ones(F, D), torch.Generator().manual_seed(0))
    assert torch.equal(m.features, targets)
    norm = Normalizer.from_dict(ck.normalizer)
    assert torch.allclose(m.normalized, norm.normalize(targets), atol=1e-6)
    assert m.positions.shape == (F, J, 3)


@pytest.mark.parametrize("delta", [False, True])
def test_partial_inpainting_keeps_the_mask_and_samples_the_rest(tmp_path, delta):
    ck = tiny_ckpt(tmp_path, delta=delta)
    B, F = 2, 5
    targets = torch.full((F, D), float("nan"))
    mask = torch.zeros(D, dtype=torch.bool)
    mask[:3] = True  # root velocity and yaw rate only
    targets[:, :3] = torch.tensor([0.04, 0.0, 0.01])
    m = C.inpaint(ck, start_state(B), targets, mask, torch.Generator().manual_seed(0))
    assert m.positions.shape == (B, F, J, 3)
    assert torch.equal(m.features[..., :3], targets[:, :3].expand(B, F, 3))
    assert torch.isfinite(m.features).all()
    assert not torch.allclose(m.features[0, :, 3:], m.features[1, :, 3:])  # free, stochastic
    # stopping early (t_stop) makes the constraint soft: close, not equal
    soft = C.inpaint(ck, start_state(B), targets, mask, torch.Generator().manual_seed(0), t_stop=2)
    assert not torch.equal(soft.features[..., :3], m.features[..., :3])


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3)), min_size=2, max_size=12),
    st.floats(0.5, 3.0),
)
def test_root_path_targets_decode_to_the_path(points, speed):
    pts = torch.tensor(points, dtype=torch.float64)
    if (pts[1:] - pts[:-1]).norm(dim=1).sum() < 1e-3:
        return
    path = C.polyline_path(pts, speed)
    con = C.root_path_targets(LAYOUT, path)
    xy, heading = decode_root(con.targets.double(), con.start_pose)
    assert torch.allclose(xy.float(), path[1:], atol=1e-4)
    assert con.mask[:, :5].all() and not con.mask[:, 5:].any()  # root velocity, yaw, root x y
    assert (con.targets[:, 3:5] == 0).all()
    step = (path[1:] - path[:-1]).double()
    moving = step.norm(dim=1) > 1e-4
    h = torch.atan2(step[:, 1], step[:, 0])  # heading = direction of travel
    assert torch.allclose(
        torch.cos(heading - h)[moving],
        torch.ones(int(moving.sum()), dtype=torch.float64),
        atol=1e-4,
    )


def test_path_helpers_and_joint_constraints():
    circle = C.circle_path(2.0, 1.0, 90)
    assert circle.shape == (91, 2)
    steps = (circle[1:] - circle[:-1]).norm(dim=1) * 30
    assert torch.allclose(steps, torch.full_like(steps, 1.0), atol=1e-3)  # 1 m/s
    assert torch.allclose((circle - torch.tensor([0.0, 2.0])).norm(dim=1), torch.tensor(2.0))
    eight = C.figure_eight_path(1.0, 1.0, 400)
    assert eight[:, 1].max() > 1.9 and eight[:, 1].min() < -1.9
    head = C.joint_height_targets(LAYOUT, "head", torch.full((90,), 1.4))
    root = C.root_path_targets(LAYOUT, circle)
    both = root | head
    assert both.mask.sum() == 90 * 6 and both.start_pose is not None
    world = torch.cat([circle[1:], torch.full((90, 1), 1.5)], 1)  # the head right above the root
    con = C.joint_path_targets(LAYOUT, "head", world, root)
    from minimdm.motion.features import decode

    pos = decode(con.targets.double(), con.start_pose)  # only root and head are specified
    assert torch.allclose(pos[:, 1].float(), world, atol=1e-4)


# ------------------------------------------------------------------ beam search


def test_beam_search_commits_the_first_frame_of_the_best_candidate(tmp_path):
    ck = tiny_ckpt(tmp_path)
    seen = []

    def score(future):  # prefer the fastest forward root velocity over the horizon
        seen.append(future)
        return future.features[..., 0].sum(-1)

    P, H, F = 5, 3, 4
    m = C.beam_search(
        ck, start_state(), score, F, pool=P, horizon=H, generator=torch.Generator().manual_seed(0)
    )
    assert len(seen) == F and seen[0].features.shape == (1, P, H, D)
    for f, fut in enumerate(seen):
        best = fut.features[0, :, :, 0].sum(-1).argmax()
        assert torch.allclose(m.features[f], fut.features[0, best, 0], atol=1e-5)
        assert fut.frame == f
    # candidates start from the committed pose
    assert torch.allclose(seen[1].start_xy[0].float(), m.root_xy[0], atol=1e-5)
    assert m.positions.shape == (F, J, 3) and m.info["score"].shape == (F,)


def test_beam_search_commits_several_frames_of_the_best_plan(tmp_path):
    ck = tiny_ckpt(tmp_path)
    seen = []

    def score(future):
        seen.append(future)
        return -future.features[..., 1].abs().sum(-1)

    g = torch.Generator().manual_seed(0)
    m = C.beam_search(ck, start_state(2), score, 7, pool=3, horizon=3, commit=3, generator=g)
    assert [fut.frame for fut in seen] == [0, 3, 6]  # one search per 3 kept frames
    for fut in seen:
        best = (-fut.features[..., 1].abs().sum(-1)).argmax(1)  # (b,)
        for i in range(2):
            kept = m.features[i, fut.frame : fut.frame + 3]
            assert torch.allclose(kept, fut.features[i, best[i], : len(kept)], atol=1e-5)
    with pytest.raises(ValueError, match=r"commit must lie in \[1, horizon=3\], got 4"):
        C.beam_search(ck, start_state(), score, 7, pool=3, horizon=3, commit=4)


def test_scores_rank_candidates():
    xy = torch.zeros(2, 2, dtype=torch.float64)
    feats = torch.zeros(2, 3, 1, D)
    feats[:, 0, 0, 0] = 0.10  # candidate 0: 10 cm forward (+x)
    feats[:, 1, 0, 1] = 0.05  # candidate 1: 5 cm left (+y)
    feats[:, 2, 0, 0] = -0.02  # candidate 2: 2 cm back
    fut = C.Future(feats, xy, torch.zeros(2, dtype=torch.float64), torch.arange(2), 0, 30.0)
    goals = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    assert C.target_score(goals)(fut).argmax(1).tolist() == [0, 1]
    assert torch.allclose(
        C.speed_score(1.5)(fut)[0], torch.tensor([-1.5, -0.0, -0.9], dtype=torch.float64), atol=1e-6
    )
    assert C.heading_score(0.0)(fut).shape == (2, 3)
    both = C.combine(C.target_score(goals), (10.0, C.speed_score(0.6)))
    assert both(fut).argmax(1).tolist() == [2, 2]  # 0.6 m/s dominates
    assert C.reached(goals, 0.95)(
        C.Future(feats[:, :1], xy, xy[:, 0], torch.arange(2), 0)
    ).tolist() == [True, False]


def test_mse_baseline_needs_noise_for_distinct_candidates():
    torch.manual_seed(0)
    mse = MLPRegressor(D, D, width=16, depth=3)
    futures = []

    def keep(f):  # keeps the candidates, scores them by their first feature
        futures.append(f)
        return f.features[..., 0, 0]

    C.beam_search(mse, start_state(), keep, 2, pool=4)
    assert torch.equal(futures[0].features[0, 0], futures[0].features[0, 3])  # all identical
    futures.clear()
    noisy = Sampler.load(mse, noise=0.1)
    C.beam_search(noisy, start_state(), keep, 2, pool=4, generator=torch.Generator().manual_seed(0))
    assert not torch.equal(futures[0].features[0, 0], futures[0].features[0, 3])
    mvae = MVAE(MVAEConfig(D, D, latent_dim=4, width=16, depth=3))
    g = torch.Generator().manual_seed(0)
    m = C.beam_search(mvae, start_state(3), lambda f: f.features[..., 0, 0], 2, pool=4, generator=g)
    assert m.positions.shape == (3, 2, J, 3)


# ------------------------------------------------------------------ bad input


def test_bad_input_raises_with_the_expected_values(tmp_path):
    ck = tiny_ckpt(tmp_path)
    s = start_state()
    score = C.target_score([1.0, 0.0])
    with pytest.raises(ValueError, match="pool must be an integer >= 1, got 0"):
        C.beam_search(ck, s, score, 3, pool=0)
    with pytest.raises(ValueError, match="horizon must be an integer >= 1, got 0"):
        C.beam_search(ck, s, score, 3, horizon=0)
    with pytest.raises(ValueError, match="n_frames must be an integer >= 1"):
        C.beam_search(ck, s, score, 0)
    with pytest.raises(ValueError, match=r"score_fn must return shape \(b=1, P=4\)"):
        C.beam_search(ck, s, lambda f: torch.zeros(4), 2, pool=4)
    with pytest.raises(ValueError, match=rf"start must have shape \({D},\)"):
        C.beam_search(ck, torch.zeros(D + 1), score, 2)
    with pytest.raises(
        ValueError,
        match=rf"mask must have last dim D={D} \(the feature dimension\), got shape \(3, {D - 1}\)",
    ):
        C.inpaint(ck, s, torch.zeros(3, D), torch.ones(3, D - 1))
    with pytest.raises(ValueError, match=r"mask must have 3 frames"):
        C.inpaint(ck, s, torch.zeros(3, D), torch.ones(4, D))
    bad = torch.zeros(3, D)
    bad[1, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN/Inf where the mask is set: character 0, frame 2"):
        C.inpaint(ck, s, bad, torch.ones(D))
    with pytest.raises(ValueError, match="beyond the horizon: frames run 1..n_frames=10"):
        C.inbetween(ck, s, torch.zeros(D), 10, at=12)
    with pytest.raises(ValueError, match=rf"keyframe must have shape \({D},\)"):
        C.inbetween(ck, s, torch.zeros(D + 12), 10)
    with pytest.raises(ValueError, match="increasing"):
        C.inbetween(ck, s, torch.zeros(2, D), 10, at=[5, 5])
    with pytest.raises(ValueError, match="needs a diffusion model, got MLPRegressor"):
        C.inpaint(MLPRegressor(D, D, 8, 2), s, torch.zeros(2, D), torch.ones(D))
    with pytest.raises(ValueError, match="path must hold at least 2 points, got 1"):
        C.root_path_targets(LAYOUT, [[0.0, 0.0]])
    with pytest.raises(ValueError, match="path must be finite, but point 1 holds NaN"):
        C.root_path_targets(LAYOUT, [[0.0, 0.0], [float("nan"), 1.0], [1.0, 1.0]])
    with pytest.raises(ValueError, match=r"joint must be one of \['root', 'head'\], got 'tail'"):
        C.joint_height_targets(LAYOUT, "tail", [1.0])
    with pytest.raises(ValueError, match="speed must be > 0"):
        C.circle_path(1.0, 0.0, 10)


def test_keyframe_from_another_skeleton_raises():
    from minimdm.motion.data import Clip

    sk = Skeleton(["pelvis", "head"], [-1, 0], [[0, 0, 0], [0, 0, 0.5]])
    quats = torch.zeros(3, 2, 4)
    quats[..., 0] = 1
    clip = Clip("other", 30.0, sk, torch.zeros(3, 3).numpy(), quats.numpy())
    with pytest.raises(
        ValueError, match=r"skeleton \['pelvis', 'head'\], but the model expects \['root', 'head'\]"
    ):
        C.clip_frame(clip, 1, LAYOUT)
    assert C.clip_frame(clip, 1).shape == (D,)


# ------------------------------------------------------------------ behaviour of a trained model


@pytest.fixture(scope="module")
def walker(tmp_path_factory):
    """A tiny A-MDM trained for a few seconds on walking and running clips.

    It predicts eps: at this size the x0-predicting model continues each clip almost
    deterministically, leaving a pool of candidates nothing to choose from.
    """
    with num_threads(1):
        return _train_walker(tmp_path_factory)


def _train_walker(tmp_path_factory):
    from minimdm.amdm.train import TrainConfig, train_amdm
    from minimdm.motion import data, features

    names = ["walk", "walker/turn_left0", "walker/turn_right0", "run"]
    clips = data.load_clips(fps=30, loop_frames=150, names=names)
    arr = [features.encode(c) for c in clips]
    norm = features.Normalizer.fit(arr)
    net = dict(width=128, depth=3, time_dim=32, T=10, predicts="eps")
    steps = dict(total_steps=500, batch_size=64, rollout=2, teacher_steps=250, ramp_steps=150)
    opt = dict(lr=1e-3, lr_min=1e-4, ema_decay=0.99, eval_interval=0, ckpt_interval=0)
    cfg = TrainConfig(**net, **steps, **opt)
    layout = features.FeatureLayout.for_skeleton(clips.skeleton)
    out = tmp_path_factory.mktemp("walker")
    data = [norm.normalize(a) for a in arr]
    res = train_amdm(
        cfg, out, data, normalizer=norm, skeleton=clips.skeleton, layout=layout, progress=False
    )
    return res.checkpoint, clips


def test_beam_search_reaches_a_nearby_target(walker):
    ck, clips = walker
    cm = Sampler.load(ck)
    start = C.clip_frame(clips["walk"], 10, cm.layout)
    goal = torch.tensor([1.5, 1.0])
    g = torch.Generator().manual_seed(0)
    score, stop = C.target_score(goal), C.reached(goal)
    m = C.beam_search(ck, start, score, 150, pool=16, horizon=4, generator=g, stop_fn=stop)
    assert m.info["done_at"] > 0  # reached within 15 cm
    assert (m.root_xy[-1] - goal).norm() <= 0.15
    assert m.positions.shape == (m.info["done_at"], 15, 3)


def test_inbetweening_lands_on_the_keyframe(walker):
    ck, clips = walker
    cm = Sampler.load(ck)
    start = C.clip_frame(clips["walk"], 10, cm.layout)
    key = C.clip_frame(clips["run"], 12, cm.layout)
    B, N = 8, 30
    m = C.inbetween(ck, start.expand(B, -1), key, N, torch.Generator().manual_seed(0))
    pos = cm.layout.joint_pos
    err = (m.features[:, -1, pos] - key[pos]).unflatten(-1, (15, 3)).norm(dim=-1).mean() * 100
    free = rollout(ck, start[None], N, B, generator=torch.Generator().manual_seed(0))
    err_free = (free.features[0, :, -1, pos] - key[pos]).unflatten(-1, (15, 3)).norm(
        dim=-1
    ).mean() * 100
    # measured over seeds 0-5: 1.8-2.2 cm (mean of 8 samples), 45 cm for random sampling
    assert err < 4.0, err
    assert err_free > 3 * err
    # DDIM: each frame's chain starts at its t_0 and follows the DDIM grid below it
    ddim = Sampler.load(ck, steps=cm.schedule.T // 2, eta=1.0)
    m = C.inbetween(ddim, start.expand(B, -1), key, N, torch.Generator().manual_seed(0))
    err_ddim = (m.features[:, -1, pos] - key[pos]).unflatten(-1, (15, 3)).norm(dim=-1).mean() * 100
    assert err_ddim < 4.0 and err_free > 3 * err_ddim, (err_ddim, err_free)


# ------------------------------------------------------------------ the one rollout loop


def _old_beam(cm, x0, score_fn, n_frames, P, H, generator, commit, stop_fn):
    """Beam search's loops as they were before the one loop (a reference copy for the test):
    -> normalized frames (B, F, D) before holding, best scores (B, F), done_at (B,)."""
    from minimdm.control.beam import Future

    B, D = x0.shape
    xy, heading = torch.zeros(B, 2, dtype=torch.float64), torch.zeros(B, dtype=torch.float64)
    cond = cm.normalize(x0)
    out = torch.full((B, n_frames, D), float("nan"))
    best_scores = torch.full((B, n_frames), float("nan"))
    done_at = torch.full((B,), -1, dtype=torch.long)
    active, f = torch.arange(B), 0
    while f < n_frames and active.numel() > 0:
        b = active.numel()
        c = cond[active].repeat_interleave(P, dim=0)
        cand = torch.empty(b * P, H, D, dtype=c.dtype, device=c.device)
        for h in range(H):
            c = cm.frame(c, generator)
            cand[:, h] = c
        cand = cand.reshape(b, P, H, D)
        future = Future(cm.denormalize(cand).float(), xy[active], heading[active], active, f)
        scores = torch.as_tensor(score_fn(future)).to("cpu", torch.float64)
        best = scores.argmax(dim=1)
        plan = cand[torch.arange(b), best]
        plan_feats = future.features[torch.arange(b), best]
        best_score = scores[torch.arange(b), best].float()
        going = torch.arange(b)
        for j in range(min(commit, n_frames - f)):
            rows = active[going]
            out[rows, f + j] = plan[going, j].float()
            cond[rows] = plan[going, j]
            best_scores[rows, f + j] = best_score[going]
            step = Future(plan_feats[going, j][:, None, None], xy[rows], heading[rows], rows, f + j)
            xy[rows], heading[rows] = step.root_xy[:, 0, 0], step.heading[:, 0, 0]
            if stop_fn is not None:
                stop = torch.as_tensor(stop_fn(step), dtype=torch.bool).reshape(-1)
                done_at[rows[stop]] = f + j + 1
                going = going[~stop]
        f += min(commit, n_frames - f)
        active = active[done_at[active] < 0]
    return out, best_scores, done_at


@pytest.mark.parametrize("H,commit", [(1, 1), (3, 2)])
def test_beam_search_is_bit_identical_to_the_old_loops(tmp_path, H, commit):
    cm = Sampler.load(tiny_ckpt(tmp_path))

    def score(future):
        return future.features[..., 0].sum(-1)

    def stop(now):  # character 0 completes its task after its 3rd frame, the others never
        return (now.index == 0) & torch.tensor(now.frame >= 2)

    x0 = start_state(3)
    search = dict(pool=4, horizon=H, commit=commit, stop_fn=stop)
    m = C.beam_search(cm, x0, score, 7, **search, generator=torch.Generator().manual_seed(3))
    out, scores, done_at = _old_beam(
        cm, x0, score, 7, 4, H, torch.Generator().manual_seed(3), commit, stop
    )
    assert done_at.tolist() == m.info["done_at"].tolist() and done_at[0] >= 3
    assert torch.equal(m.normalized[1:], out[1:])  # characters that kept searching
    k = int(done_at[0])
    assert torch.equal(m.normalized[0, :k], out[0, :k])  # and the first until it was done
    torch.testing.assert_close(m.info["score"], scores.float(), rtol=0, atol=0, equal_nan=True)
    # when every character is done the search stops: one character, the motion ends there
    m1 = C.beam_search(cm, x0[0], score, 7, **search, generator=torch.Generator().manual_seed(3))
    assert m1.n_frames == m1.info["done_at"] == k


def test_inpaint_and_inbetween_are_bit_identical_to_the_old_loops(tmp_path):
    cm = Sampler.load(tiny_ckpt(tmp_path))
    x0 = start_state(2)
    tgt = torch.randn(5, D, generator=torch.Generator().manual_seed(2))
    mask = torch.zeros(D, dtype=torch.bool)
    mask[:3] = True
    m = C.inpaint(cm, x0, tgt, mask, torch.Generator().manual_seed(1), t_stop=1)
    g = torch.Generator().manual_seed(1)  # the old loop, a reference copy
    tgt_n, cond, old = cm.normalize(tgt.expand(2, 5, D)), cm.normalize(x0), []
    for f in range(5):
        hook = C.inpaint_hook(cm.schedule, tgt_n[:, f], mask.expand(2, D), g, 1)
        cond = cm.frame(cond, g, hook=hook)
        old.append(cond)
    assert torch.equal(m.normalized, torch.stack(old, 1))

    keys = torch.randn(2, D, generator=torch.Generator().manual_seed(5)) * 0.1
    m = C.inbetween(cm, x0, keys, 6, torch.Generator().manual_seed(1), at=[2, 4])
    g = torch.Generator().manual_seed(1)
    keys_n, cond, old, k, prev = cm.normalize(keys), cm.normalize(x0), [], 0, 0
    ats, T = [2, 4], cm.schedule.T
    for f in range(1, 7):
        if k < 2:
            t0 = C.inbetween_t_start(f - prev, ats[k] - prev, T)
            x_start = q_sample(cm.schedule, keys_n[k].expand(2, D), t0, generator=g)
            cond = cm.frame(cond, g, t_start=t0, x_start=x_start)
            if f == ats[k]:
                k, prev = k + 1, f
        else:
            cond = cm.frame(cond, g)
        old.append(cond)
    assert torch.equal(m.normalized, torch.stack(old, 1))


@pytest.mark.parametrize("k", [1, 3])
def test_every_technique_names_the_frame_where_the_model_returns_nan(tmp_path, monkeypatch, k):
    from minimdm.amdm.sampling import NonFiniteFrameError

    calls, frame = [], Sampler.frame

    def poisoned(*args, **kwargs):  # NaN in batch row 1 from the k-th frame on
        x = frame(*args, **kwargs)
        calls.append(1)
        if len(calls) >= k:
            x = x.clone()
            x[1, 0] = float("nan")
        return x

    monkeypatch.setattr(Sampler, "frame", poisoned)
    ck, x0 = tiny_ckpt(tmp_path), start_state(2)
    runs = {
        r"beam search .*frame {k} .*character 0, candidate 1": lambda: C.beam_search(
            ck, x0, lambda fut: fut.features[..., 0].sum(-1), 5, pool=3
        ),
        r"inpaint .*frame {k} .*character 1": lambda: C.inpaint(
            ck, x0, torch.zeros(5, D), torch.zeros(D)
        ),
        r"inbetween .*frame {k} .*character 1": lambda: C.inbetween(ck, x0, x0[0], 5),
    }
    for pattern, run in runs.items():
        calls.clear()
        with pytest.raises(NonFiniteFrameError, match=pattern.format(k=k)) as e:
            run()
        assert e.value.frame == k
