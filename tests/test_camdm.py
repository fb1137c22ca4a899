"""CAMDM (chapter 9): the token layout, CFG on past motion (eq. 5) on the one reverse chain, the
run-time trajectories (spring, HFTE), training, the controller on the one rollout loop, the style
classifier's Fréchet distance, bad input and the shipped checkpoints.

Everything but the shipped checkpoints runs on tiny networks and a synthetic 4-joint walker.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import minimdm
from minimdm.amdm.sampling import NonFiniteFrameError
from minimdm.camdm import controller as camdm_controller
from minimdm.camdm.classifier import frechet_distance, load_classifier
from minimdm.camdm.controller import CAMDMController, Commands, ControlConfig
from minimdm.camdm.data import (
    CAMDMLayout,
    orthonormalize,
    to_canonical,
    to_world,
    trajectory_of,
    world_frames,
)
from minimdm.camdm.model import CAMDM, CAMDMConfig, Conditions
from minimdm.camdm.sampling import GuidedStep, guided_x0, sample_future
from minimdm.camdm.train import (
    CAMDMTrainConfig,
    data_from_clips,
    load_camdm,
    train_camdm,
    window_weights,
)
from minimdm.camdm.trajectory import (
    extend_trajectory,
    inertialize,
    spring_headings,
    spring_path,
    spring_positions,
)
from minimdm.checkpoint import CheckpointMismatchError
from minimdm.cli import main
from minimdm.diffusion import DDPMStep, NoiseSchedule, reverse_chain
from minimdm.motion.data import Clip
from minimdm.motion.skeleton import Skeleton, axis_angle_to_quat
from minimdm.validate import InputError, InputTypeError, MismatchError

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

P, F, J = 4, 6, 4
D = 3 + 6 * J


def walker(style: str, n: int = 40, names=("Hips", "Spine", "LegL", "LegR"), speed=0.04) -> Clip:
    """A 4-joint body walking along +x, legs swinging; 'big' swings wider than 'small'."""
    offsets = np.array([[0, 0, 0.9], [0, 0, 0.3], [0, 0.1, -0.85], [0, -0.1, -0.85]], float)
    sk = Skeleton(list(names), [-1, 0, 0, 0], offsets, foot_joints=[names[2], names[3]])
    amp = 0.5 if style == "big" else 0.2
    ph = np.arange(n) * 0.3
    aa = np.zeros((n, J, 3))
    aa[:, 2, 1], aa[:, 3, 1] = amp * np.sin(ph), -amp * np.sin(ph)
    root = np.stack([np.arange(n) * speed, np.zeros(n), np.full(n, 0.9)], -1)
    clip = Clip(f"walk_{style}", 30.0, sk, root, axis_angle_to_quat(torch.tensor(aa)).numpy())
    clip.labels = {"content": "walk", "style": style}
    return clip


def tiny_config(**kw) -> CAMDMTrainConfig:
    base = dict(latent=16, layers=1, heads=2, ff=32, dropout=0.0, past=P, future=F, T=4)
    base |= dict(batch_size=16, total_steps=60, warmup_steps=5, lr=3e-3, log_interval=10)
    base |= dict(eval_interval=0, ckpt_interval=0, ema_decay=0.0, p_drop_style=0.1)
    return CAMDMTrainConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny CAMDM trained for 60 steps on two synthetic styles, and its data."""
    config = tiny_config()
    data = data_from_clips([walker("big"), walker("small", speed=0.02)], config, [walker("big")])
    out = tmp_path_factory.mktemp("camdm")
    with torch.random.fork_rng():
        ckpt = train_camdm(config, out, data=data, progress=False)
    return ckpt, data


def conditions(B: int = 3, seed: int = 0, n_styles: int = 2) -> Conditions:
    g = torch.Generator().manual_seed(seed)
    return Conditions(
        torch.randn(B, P, D, generator=g),
        torch.randint(n_styles, (B,), generator=g),
        torch.randn(B, F, 4, generator=g),
    )


def net(tokens: str = "separate", backbone: str = "transformer") -> CAMDM:
    torch.manual_seed(0)
    size = dict(latent=16, layers=1, heads=2, ff=32, dropout=0.0)
    return CAMDM(CAMDMConfig(D, 2, P, F, **size, tokens=tokens, backbone=backbone)).eval()


# ------------------------------------------------------------------------------ token layout


@settings(max_examples=20, deadline=None)
@given(which=st.sampled_from(["t", "style", "past", "traj", "frame"]), seed=st.integers(0, 99))
def test_each_condition_reaches_its_own_token(which, seed):
    """Separate condition tokenization (§3.2): changing one condition changes its token alone,
    before attention mixes them."""
    model, cond = net(), conditions(seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    x, t = torch.randn(3, F, D, generator=g), torch.tensor([0, 1, 2])
    base = model.tokens(x, t, cond)  # (B, 4 + F, L)
    frame = seed % F
    if which == "t":
        t, expected = t + 1, {0}
    elif which == "style":
        cond.style, expected = 1 - cond.style, {1}
    elif which == "past":
        cond.past, expected = cond.past + torch.randn(cond.past.shape, generator=g), {2}
    elif which == "traj":
        cond.traj, expected = cond.traj + torch.randn(cond.traj.shape, generator=g), {3}
    else:
        x = x.clone()
        x[:, frame] += 1.0
        expected = {4 + frame}
    changed = (model.tokens(x, t, cond) - base).abs().amax(dim=(0, 2)) > 0
    assert set(changed.nonzero()[:, 0].tolist()) == expected


def test_past_frames_tokens_give_each_past_frame_its_own_token():
    model, cond = net("past_frames"), conditions()
    x, t = torch.randn(3, F, D), torch.zeros(3, dtype=torch.long)
    base = model.tokens(x, t, cond)
    assert base.shape[1] == 2 + P + 1 + F
    for what, want in (("past", {2 + P - 1}), ("traj", {2 + P})):
        c = conditions()
        if what == "past":
            c.past = c.past.clone()
            c.past[:, -1] += 1.0  # the last past frame only
        else:
            c.traj = c.traj + 1.0
        changed = (model.tokens(x, t, c) - base).abs().amax(dim=(0, 2)) > 0
        assert set(changed.nonzero()[:, 0].tolist()) == want


def test_a_single_token_fuses_every_condition_and_the_mlp_has_none():
    model, cond = net("single"), conditions()
    x, t = torch.randn(3, F, D), torch.zeros(3, dtype=torch.long)
    base = model.tokens(x, t, cond)
    assert base.shape[1] == 1 + F
    cond.past = cond.past + 1
    changed = (model.tokens(x, t, cond) - base).abs().amax(dim=(0, 2)) > 0
    assert changed.nonzero()[:, 0].tolist() == [0]
    mlp = net(backbone="mlp")
    assert mlp(x, t, conditions()).shape == (3, F, D)
    with pytest.raises(ValueError, match="no tokens"):
        mlp.tokens(x, t, cond)


def test_a_dropped_past_is_the_learned_null():
    model, cond = net(), conditions()
    x, t = torch.randn(3, F, D), torch.zeros(3, dtype=torch.long)
    dropped = cond.without("past")
    other = Conditions(torch.randn(3, P, D), cond.style, cond.traj, dropped.keep_past)
    assert torch.equal(model(x, t, dropped), model(x, t, other))  # the past is not seen
    assert not torch.equal(model(x, t, dropped), model(x, t, cond))


# ------------------------------------------------------------------------------ CFG (eq. 5)


@pytest.mark.parametrize("guide", ["past", "style"])
def test_cfg_at_gamma_one_is_the_conditional_model_exactly(guide):
    model, cond = net(), conditions()
    schedule = NoiseSchedule("cosine", 8)
    guided = sample_future(model, schedule, cond, torch.Generator().manual_seed(3), guide=guide)
    g = torch.Generator().manual_seed(3)
    x = torch.randn((3, F, D), generator=g)
    plain = reverse_chain(DDPMStep(model, schedule, "x0"), x, range(7, -1, -1), cond, g)
    assert torch.equal(guided, plain)


@settings(max_examples=10, deadline=None)
@given(
    gamma=st.floats(0.0, 2.0).filter(lambda g: g != 1.0), guide=st.sampled_from(["past", "style"])
)
def test_cfg_combines_both_halves_of_one_forward_pass(gamma, guide):
    """Eq. 5: G(∅) + γ (G(p) - G(∅)), both from one call on the doubled batch."""
    model, cond = net(), conditions()
    x, t = torch.randn(3, F, D), torch.tensor([1, 2, 3])
    calls = []
    model.register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
    out = guided_x0(model, x, t, cond, gamma, guide)
    assert calls == [6]  # one forward pass on 2 B rows
    with torch.no_grad():
        full, dropped = model(x, t, cond), model(x, t, cond.without(guide))
    torch.testing.assert_close(out, dropped + gamma * (full - dropped), atol=1e-5, rtol=1e-5)


def test_cfg_scales_per_sample_leave_gamma_one_rows_conditional():
    model, cond = net(), conditions()
    x, t = torch.randn(3, F, D), torch.tensor([1, 1, 1])
    out = guided_x0(model, x, t, cond, torch.tensor([1.0, 0.7, 1.0]), "past")
    full = model(x, t, cond)
    torch.testing.assert_close(out[[0, 2]], full[[0, 2]], atol=1e-5, rtol=1e-5)
    assert (out[1] - full[1]).abs().max() > 1e-3
    assert GuidedStep(model, NoiseSchedule("cosine", 8)).name == "cfg"


def test_cfg_guides_each_sample_on_its_own_condition():
    """A (B,) bool guide: rows marked True guide on the style, the others on the past, still in
    one forward pass of 2 B rows; each row equals the single-guide result for that row."""
    model, cond = net(), conditions()
    x, t = torch.randn(3, F, D), torch.tensor([2, 2, 2])
    on_style = torch.tensor([True, False, True])
    calls = []
    model.register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
    out = guided_x0(model, x, t, cond, 2.0, on_style)
    assert calls == [6]
    with torch.no_grad():
        by_style, by_past = (guided_x0(model, x, t, cond, 2.0, g) for g in ("style", "past"))
    torch.testing.assert_close(out[on_style], by_style[on_style], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out[~on_style], by_past[~on_style], atol=1e-5, rtol=1e-5)
    assert (by_style - by_past).abs().max() > 1e-3  # the two guides differ on this model
    for bad in (torch.tensor([1, 0, 1]), torch.tensor([True, False]), "trajectory"):
        with pytest.raises(InputError, match="guide must be 'past'"):
            guided_x0(model, x, t, cond, 2.0, bad)


# ------------------------------------------------------------------------------ trajectories


@settings(max_examples=30, deadline=None)
@given(
    heading=st.floats(-math.pi, math.pi),
    step=st.floats(0.005, 0.1),
    side=st.floats(-math.pi / 2, math.pi / 2),
    n=st.integers(3, 30),
    length=st.integers(31, 70),
)
def test_hfte_extends_a_straight_line_straight(heading, step, side, n, length):
    """A path along ``heading``, facing ``heading + side`` (a sideways walk), stays on its line
    with the same spacing and facing."""
    d = torch.tensor([math.cos(heading), math.sin(heading)], dtype=torch.float64)
    xy = (torch.arange(n, dtype=torch.float64)[:, None] * step * d)[None]
    h = torch.full((1, n), heading + side, dtype=torch.float64)
    ext_xy, ext_h = extend_trajectory(xy, h, length, K=15)
    want = (torch.arange(length, dtype=torch.float64)[:, None] * step * d)[None]
    torch.testing.assert_close(ext_xy, want, atol=1e-9, rtol=0)
    torch.testing.assert_close(ext_h, torch.full((1, length), heading + side, dtype=torch.float64))


@settings(max_examples=30, deadline=None)
@given(
    radius=st.floats(0.5, 5.0),
    dtheta=st.floats(-0.05, 0.05).filter(lambda a: abs(a) > 1e-3),
    n=st.integers(16, 45),
)
def test_hfte_keeps_the_curvature_of_a_circle(radius, dtheta, n):
    a = torch.arange(n, dtype=torch.float64) * dtheta
    xy = torch.stack([radius * torch.sin(a), radius * (1 - torch.cos(a))], -1)[None]
    h = a[None].clone()  # facing along the circle
    if dtheta < 0:  # clockwise: the centre lies to the right
        xy = torch.stack([radius * torch.sin(-a), -radius * (1 - torch.cos(a))], -1)[None]
    centre = torch.tensor([0.0, radius if dtheta > 0 else -radius], dtype=torch.float64)
    ext_xy, ext_h = extend_trajectory(xy, h, n + 30, K=15)
    r = (ext_xy[0] - centre).norm(dim=-1)
    torch.testing.assert_close(r, torch.full_like(r, radius), atol=1e-3 * radius, rtol=0)
    turn = torch.diff(ext_h[0])  # the heading keeps turning at the same rate
    torch.testing.assert_close(turn, torch.full_like(turn, dtheta), atol=1e-9, rtol=0)
    step = torch.diff(ext_xy[0], dim=0).norm(dim=-1)  # and the spacing stays
    torch.testing.assert_close(step, torch.full_like(step, step[0].item()), atol=1e-3, rtol=1e-3)


def test_springs_reach_the_joystick():
    t = torch.arange(1, 91, dtype=torch.float64) / 30
    xy = spring_positions(torch.zeros(1, 2), torch.zeros(1, 2), torch.tensor([[1.0, 0.0]]), 0.3, t)
    v = torch.diff(xy[0], dim=0)[-1] * 30
    torch.testing.assert_close(v, torch.tensor([1.0, 0.0]), atol=1e-3, rtol=0)
    assert torch.equal(xy[0, :, 1], torch.zeros(90))
    # a turn from 170 to -170 degrees goes the short way, through 180
    h0, h1 = torch.tensor([math.radians(170)]), torch.tensor([math.radians(-170)])
    h = spring_headings(h0, torch.zeros(1), h1, 0.3, t)
    assert h[0].diff().min() >= 0 and abs(h[0, -1].item() - math.radians(190)) < 1e-3


vel = st.tuples(st.floats(-3, 3), st.floats(-3, 3))


@settings(max_examples=25, deadline=None)
@given(g0=vel, g1=vel, halflife=st.floats(0.1, 1.0))
def test_the_stepped_spring_path_moves_as_the_closed_form_spring(g0, g1, halflife):
    """A joystick that holds g0 for a frame, then g1: the path's velocity after the change is
    the closed-form spring's (the derivative of spring_positions from g0 towards g1)."""
    dt, N = 1 / 30, 60
    goal = torch.tensor([g0], dtype=torch.float64)[:, None].repeat(1, N, 1)
    goal[:, 1:] = torch.tensor(g1, dtype=torch.float64)
    path = spring_path(goal, halflife, dt)
    assert path.shape == (1, N + 1, 2) and torch.equal(path[0, 0], torch.zeros(2).double())
    v = torch.diff(path[0], dim=0) / dt  # (N, 2): the velocity at the end of each step

    def x(t):
        return spring_positions(torch.zeros(1, 2).double(), goal[:, 0], goal[:, 1], halflife, t)

    t, h = torch.arange(1, N, dtype=torch.float64) * dt, 1e-6
    torch.testing.assert_close(v[0], goal[0, 0])
    torch.testing.assert_close(v[1:], ((x(t + h) - x(t - h)) / (2 * h))[0], atol=1e-6, rtol=0)


# ------------------------------------------------------------------------------ representation


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 99), halflife=st.floats(0.05, 0.5))
def test_inertialize_starts_on_the_source_and_ends_on_the_target(seed, halflife):
    g = torch.Generator().manual_seed(seed)
    source, target = torch.randn(2, 2, D, generator=g), torch.randn(2, 60, D, generator=g)
    fps = 30.0
    out = inertialize(source, target, halflife, fps)
    assert torch.allclose(out[:, 0], source[:, 0], atol=1e-6)
    gap = (source[:, 0] - target[:, 0]).abs().max()
    # ten half-lives on, less than a thousandth of the gap is left
    late = round(10 * halflife * fps)
    if late < target.shape[1]:
        assert (out[:, late:] - target[:, late:]).abs().max() < 1e-3 * gap
    # the offset dies out without ringing: it changes sign at most once per feature
    offset = out - target
    flips = (offset[:, 1:].sign() * offset[:, :-1].sign() < 0).sum(1)
    assert flips.max() <= 1


def test_orthonormalize_keeps_clean_frames_and_cleans_blended_ones():
    clip = walker("big", n=5)
    w = world_frames(clip)  # (5, D)
    assert torch.allclose(orthonormalize(w), w, atol=1e-6)
    blend = orthonormalize(0.5 * (w[0] + w[3]))
    assert torch.allclose(orthonormalize(blend), blend, atol=1e-6)


def test_canonical_frames_round_trip_and_face_x():
    clip = walker("big")
    clip.root_pos[:, :2] += [3.0, -2.0]
    world = world_frames(clip)[None, :12]
    canon, xy, h = to_canonical(world, 5, clip.skeleton.lateral_axis)
    torch.testing.assert_close(to_world(canon, xy, h), world, atol=1e-5, rtol=0)
    traj = trajectory_of(canon[:, 5:6], clip.skeleton.lateral_axis)
    torch.testing.assert_close(traj[0, 0], torch.tensor([0.0, 0.0, 1.0, 0.0]), atol=1e-5, rtol=0)


# ------------------------------------------------------------------------------ training


def test_a_tiny_model_learns(tiny):
    import json

    ckpt, _ = tiny
    log = [
        json.loads(ln) for ln in (ckpt.paths.weights.parent / "log.jsonl").read_text().splitlines()
    ]
    losses = [r["loss"] for r in log if "loss" in r]
    assert losses[-1] < 0.7 * losses[0]
    assert {"samp", "pos", "foot", "vel"} <= set(log[0])
    assert any("heldout_loss" in r for r in log)


def test_training_is_deterministic(tiny, tmp_path):
    ckpt, data = tiny
    again = train_camdm(tiny_config(total_steps=20), tmp_path, data=data, progress=False)
    twice = train_camdm(tiny_config(total_steps=20), tmp_path / "b", data=data, progress=False)
    for k, v in again.model.state_dict().items():
        assert torch.equal(v, twice.model.state_dict()[k])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_training_on_a_gpu_follows_the_cpu_run(tiny, tmp_path):
    """A CPU generator feeds the GPU run the CPU run's draws: the same losses up to kernels."""
    import json

    _, data = tiny
    runs = {}
    for device in ("cpu", "cuda"):
        config = tiny_config(total_steps=20, device=device)
        ckpt = train_camdm(config, tmp_path / device, data=data, progress=False)
        assert next(ckpt.model.parameters()).device.type == device
        lines = (tmp_path / device / "log.jsonl").read_text().splitlines()
        runs[device] = [json.loads(ln)["loss"] for ln in lines if "loss" in json.loads(ln)]
    assert runs["cuda"] == pytest.approx(runs["cpu"], rel=1e-3)


def test_training_resumes_from_its_last_checkpoint(tiny, tmp_path):
    import json

    _, data = tiny
    train_camdm(tiny_config(total_steps=20), tmp_path, data=data, progress=False)
    with open(tmp_path / "log.jsonl", "a") as f:
        f.write('{"step": 21, "lo')  # a run killed while appending leaves a torn last line
    with pytest.warns(UserWarning, match="torn last log line"):
        ckpt = train_camdm(tiny_config(total_steps=30), tmp_path, data=data, progress=False)
    assert ckpt.step == 30
    steps = [json.loads(ln)["step"] for ln in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert steps == [10, 20, 20, 30, 30]  # losses every 10 steps, evaluations at the ends
    with pytest.raises(ValueError, match="cannot resume"):
        train_camdm(tiny_config(total_steps=40, latent=8), tmp_path, data=data, progress=False)


class Killed(Exception):
    pass


def _weight_bytes(path) -> bytes:
    """The tensor bytes of a safetensors file (its header also holds the training time)."""
    raw = path.read_bytes()
    return raw[8 + int.from_bytes(raw[:8], "little") :]


def test_a_run_killed_while_writing_its_log_resumes_bit_exactly(tiny, tmp_path):
    """A kill in the middle of writing a log line leaves a torn last line; the resumed run drops
    it with the records past its checkpoint and ends with the very bytes of an uninterrupted
    run: weights, EMA, optimizer and generator state, and the log itself."""
    _, data = tiny
    config = tiny_config(total_steps=30, log_interval=5, ckpt_interval=10, ema_decay=0.9)
    full, cut = tmp_path / "full", tmp_path / "cut"
    train_camdm(config, full, data=data, progress=False)

    def kill(step, record):
        if step == 15:  # the log holds steps 5, 10, 15; the last checkpoint is step 10's
            log = cut / "log.jsonl"
            text = log.read_bytes()
            log.write_bytes(text[: len(text) - 40])  # the kill lands inside step 15's line
            raise Killed

    with pytest.raises(Killed):
        train_camdm(config, cut, data=data, progress=False, callback=kill)
    with pytest.warns(UserWarning, match="torn last log line"):
        ckpt = train_camdm(config, cut, data=data, progress=False)
    assert ckpt.step == 30
    for name in ("model.safetensors", "model.train.safetensors"):
        assert _weight_bytes(cut / name) == _weight_bytes(full / name), name
    assert (cut / "log.jsonl").read_bytes() == (full / "log.jsonl").read_bytes()


# ------------------------------------------------------------------------------ the controller


def test_the_controller_replans_every_m_frames_and_at_a_style_change(tiny):
    ckpt, _ = tiny
    ctl = CAMDMController(ckpt, ControlConfig(M=3, K=3, switch_frames=4))
    ctl.reset(walker("big"), n_characters=2)
    cmd = Commands.hold([1.0, 0.0], 0.0, 0, 8, batch=2).then(
        Commands.hold([1.0, 0.0], 0.0, 1, 6, 2)
    )
    out = ctl.run(cmd, 14, torch.Generator().manual_seed(0))
    assert out.frames.shape == (2, 14, D) and out.positions.shape == (2, 14, J, 3)
    assert torch.isfinite(out.positions).all()
    assert out.replans == [0, 3, 6, 8, 11]  # every M = 3 frames, and at once at frame 8
    assert [g[0].item() for g in out.gammas] == pytest.approx([1, 1, 1, 0.7, 0.7])
    assert out.trajectories[0].shape == (2, F, 3)
    more = ctl.run(Commands.hold([1.0, 0.0], 0.0, 1, 5, 2), 5)  # continues where it stopped
    assert more.frames.shape == (2, 5, D)


def test_a_start_of_another_style_is_a_style_change(tiny):
    ckpt, _ = tiny
    ctl = CAMDMController(ckpt, ControlConfig(M=3, switch_frames=4))
    ctl.reset(walker("big"), n_characters=2, style=["big", "small"])
    out = ctl.run(Commands.hold([1.0, 0.0], 0.0, 1, 9, batch=2), 9)
    assert torch.stack(out.gammas).flatten().tolist() == pytest.approx([0.7, 1, 0.7, 1, 1, 1])
    with pytest.raises(InputError, match="one of the model's styles"):
        ctl.reset(walker("big"), style="drunk")


def test_the_controller_guides_on_the_style_and_on_the_past_after_a_change(tiny, monkeypatch):
    ckpt, _ = tiny
    config = ControlConfig(M=3, switch_frames=4, guide="style", gamma=2.0, guide_switch="past")
    ctl = CAMDMController(ckpt, config)
    seen = []
    plan = ctl.sample_plan

    def spy(past, style, trajectory, generator, gamma, guide="past"):
        seen.append((gamma.tolist(), guide.tolist()))  # gamma is float32
        return plan(past, style, trajectory, generator, gamma, guide)

    monkeypatch.setattr(ctl, "sample_plan", spy)
    ctl.reset(walker("big"), n_characters=2, style=["big", "small"])
    ctl.run(Commands.hold([1.0, 0.0], 0.0, 1, 9, batch=2), 9, torch.Generator().manual_seed(0))
    # character 0 changes style at frame 0: CFG on the past at 0.7 for the re-plans at frames 0
    # and 3 (within switch_frames), then on the style at 2 like character 1
    assert [g for _, g in seen] == [[False, True], [False, True], [True, True]]
    assert [s for s, _ in seen] == [pytest.approx([0.7, 2.0])] * 2 + [pytest.approx([2.0, 2.0])]
    with pytest.raises(InputError, match="guide_switch must be 'past' or 'style'"):
        CAMDMController(ckpt, ControlConfig(guide_switch="future"))


def test_gamma_styles_guide_the_named_style_harder_at_steady_state(tiny, monkeypatch):
    ckpt, _ = tiny
    config = ControlConfig(
        M=3, switch_frames=4, guide="style", gamma=2.0, gamma_styles={"small": 4}
    )
    ctl = CAMDMController(ckpt, config)
    seen = []
    plan = ctl.sample_plan

    def spy(past, style, trajectory, generator, gamma, guide="past"):
        seen.append(gamma.tolist())
        return plan(past, style, trajectory, generator, gamma, guide)

    monkeypatch.setattr(ctl, "sample_plan", spy)
    ctl.reset(walker("big"), n_characters=2, style=["big", "small"])
    ctl.run(Commands.hold([1.0, 0.0], 0.0, 1, 9, batch=2), 9, torch.Generator().manual_seed(0))
    # character 1 is 'small' from the start: 4 throughout; character 0 switched to 'small' at
    # frame 0: gamma_switch for the re-plans at frames 0 and 3, then its style's 4
    assert seen == [pytest.approx([0.7, 4.0])] * 2 + [pytest.approx([4.0, 4.0])]
    seen.clear()  # told to walk the other way: turning, so gamma, not the style's 4
    ctl.reset(walker("big"), n_characters=2, style=["small", "small"])
    ctl.run(Commands.hold([-1.0, 0.0], math.pi, 1, 3, batch=2), 3, torch.Generator().manual_seed(0))
    assert seen == [pytest.approx([2.0, 2.0])]


@pytest.mark.parametrize(
    "styles, error, words",
    [
        ({"drunk": 3.0}, InputError, r"gamma_styles key must be one of the model's styles"),
        ({"small": float("nan")}, InputError, r"gamma_styles\['small'\] must be a finite"),
        ({"small": -1.0}, InputError, r"gamma_styles\['small'\] must be a finite number >= 0"),
        ([("small", 3.0)], InputTypeError, r"gamma_styles must be a dict of style name"),
    ],
)
def test_bad_gamma_styles_name_the_style_and_the_field(tiny, styles, error, words):
    ckpt, _ = tiny
    with pytest.raises(error, match=words):
        CAMDMController(ckpt, ControlConfig(gamma_styles=styles))


def test_the_controller_replans_sooner_while_turning(tiny):
    """M_turning applies while a character faces further than turning_deg from its command."""
    ckpt, _ = tiny
    replans = {}
    for name, facing in (("ahead", 0.0), ("behind", math.pi)):
        ctl = CAMDMController(ckpt, ControlConfig(M=5, M_turning=2, turning_deg=45.0))
        ctl.reset(walker("big"))
        here = camdm_controller.headings(ctl.history[:, -1:], ctl.skeleton.lateral_axis)[0, 0]
        out = ctl.run(Commands.hold([1.0, 0.0], float(here) + facing, 0, 10), 10)
        replans[name] = out.replans
    assert replans["behind"] == [0, 2, 4, 6, 8]
    assert replans["ahead"] == [0, 5]  # facing the command: a plan serves M = 5 frames
    with pytest.raises(InputError, match="M_turning"):
        CAMDMController(ckpt, ControlConfig(M_turning=0))


def test_the_controller_without_hfte_still_runs(tiny):
    ckpt, _ = tiny
    ctl = CAMDMController(ckpt, ControlConfig(M=4, extend=False))
    ctl.reset(walker("small"))
    out = ctl.run(Commands.hold([0.5, 0.5], 1.0, 1, 10), 10, torch.Generator().manual_seed(1))
    assert torch.isfinite(out.frames).all() and out.replans == [0, 4, 8]


def _plans_and_sources(monkeypatch):
    """Record each new plan in the world before inertialization, and each inertialization's
    source (the old plan's next two frames)."""
    plans, sources = [], []
    to_world, inertialize_ = camdm_controller.to_world, camdm_controller.inertialize

    def recording_to_world(*args):
        plans.append(to_world(*args))
        return plans[-1]

    def recording_inertialize(source, *args):
        sources.append(source)
        return inertialize_(source, *args)

    monkeypatch.setattr(camdm_controller, "to_world", recording_to_world)
    monkeypatch.setattr(camdm_controller, "inertialize", recording_inertialize)
    return plans, sources


@pytest.mark.parametrize("halflife", [0.0, 0.15])
def test_a_replan_goes_on_from_where_the_old_plan_was_going(tiny, monkeypatch, halflife):
    """halflife_replan = 0 applies each plan untouched (the paper's controller); with a
    half-life, the first frame of each new plan is the old plan's next frame."""
    ckpt, _ = tiny
    plans, sources = _plans_and_sources(monkeypatch)
    ctl = CAMDMController(ckpt, ControlConfig(M=3, K=3, halflife_replan=halflife))
    ctl.reset(walker("big"), n_characters=2)
    cmd = Commands.hold([1.0, 0.0], 0.0, 0, 7, batch=2).then(
        Commands.hold([0.6, 0.6], 0.8, 1, 7, 2)
    )
    out = ctl.run(cmd, 14, torch.Generator().manual_seed(0))
    assert out.replans == [0, 3, 6, 7, 10, 13] and len(plans) == 6
    ends = [*out.replans[1:], 14]
    if halflife == 0:
        assert sources == []
        for r, e, plan in zip(out.replans, ends, plans, strict=True):
            assert torch.equal(out.frames[:, r:e], plan[:, : e - r])
        return
    assert len(sources) == 5  # every re-plan but the first, which has no old plan
    for r, source, plan in zip(out.replans[1:], sources, plans[1:], strict=True):
        assert torch.allclose(out.frames[:, r], source[:, 0], atol=1e-5)
        assert (out.frames[:, r] - plan[:, 0]).abs().max() > 1e-3  # not the raw new plan


def test_inertialization_removes_the_pop_of_a_jolting_planner(tiny):
    """A planner whose every plan starts 5 cm to the side of the last frame: the paper's
    controller pops at each re-plan; inertialized, the pop is gone."""
    ckpt, _ = tiny

    def jolting(past, generator, style, trajectory, gamma):  # canonical frames (B, F, D)
        future = past[:, -1:].repeat(1, F, 1)
        future[..., 0] += 0.03 * torch.arange(1, F + 1)  # walking along +x
        future[..., 1] += 0.05  # and a sideways jump at the plan's start
        return future

    accel = {}
    for halflife in (0.0, 0.15):
        config = ControlConfig(M=3, K=3, halflife_replan=halflife)
        ctl = CAMDMController(ckpt, config, planner=jolting)
        ctl.reset(walker("big"))
        out = ctl.run(Commands.hold([0.9, 0.0], 0.0, 0, 30), 30)
        x = out.positions
        a = (x[:, 2:] - 2 * x[:, 1:-1] + x[:, :-2]).norm(dim=-1).mean((0, 2))  # frames 1..28
        at = [r - 1 for r in out.replans if 0 < r < 29]
        accel[halflife] = a[at].mean().item()
    assert accel[0.0] > 0.04  # the 5 cm jump, in metres per frame^2
    assert accel[0.15] < 0.05 * accel[0.0]


def test_a_non_finite_plan_names_the_frame_and_the_character(tiny):
    """run() checks each frame it applies: a plan's NaN raises, naming the frame and the
    character, before the frame enters the history."""
    ckpt, _ = tiny
    plans = []

    def poisoned(past, generator, style, trajectory, gamma):  # the second plan: NaN for 1
        future = past[:, -1:].repeat(1, F, 1)
        if plans:
            future[1, :, 0] = float("nan")
        plans.append(future)
        return future

    ctl = CAMDMController(ckpt, ControlConfig(M=3), planner=poisoned)
    ctl.reset(walker("big"), n_characters=2)
    with pytest.raises(NonFiniteFrameError, match=r"camdm control .*frame 4 .*character 1") as e:
        ctl.run(Commands.hold([0.9, 0.0], 0.0, 0, 6, batch=2), 6)
    assert e.value.frame == 4 and e.value.row == 1 and len(plans) == 2
    assert torch.isfinite(ctl.history).all()


def test_frechet_distance():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(4000, 3, generator=g, dtype=torch.float64)
    b = torch.randn(4000, 3, generator=g, dtype=torch.float64) + torch.tensor([1.0, 0.0, 0.0])
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-6)
    assert frechet_distance(a, b) == pytest.approx(1.0, abs=0.15)


# ------------------------------------------------------------------------------ bad input


def test_an_unknown_style_lists_the_known_ones(tiny):
    ckpt, _ = tiny
    ctl = CAMDMController(ckpt)
    past, traj = torch.zeros(1, P, D), torch.zeros(1, F, 4)
    with pytest.raises(InputError, match=r"must be one of the model's styles \['big', 'small'\]"):
        ctl.plan(past, "drunk", traj)
    with pytest.raises(InputError, match=r"index in \[0, 1\]"):
        ctl.plan(past, 5, traj)


@pytest.mark.parametrize(
    "traj, words",
    [
        (torch.zeros(1, F - 1, 4), rf"trajectory must have shape \(B, {F}, 4\)"),
        (torch.zeros(1, F, 3), rf"trajectory must have shape \(B, {F}, 4\)"),
        (torch.zeros(2, F, 4), rf"trajectory must have shape \(1, {F}, 4\)"),
        (
            torch.full((1, F, 4), float("nan")),
            rf"trajectory must be finite \(shape \(B, {F}, 4\)\)",
        ),
        (torch.full((1, F, 4), float("inf")), "must be finite"),
    ],
)
def test_a_bad_trajectory_names_the_expected_shape(tiny, traj, words):
    ckpt, _ = tiny
    with pytest.raises(InputError, match=words):
        CAMDMController(ckpt).plan(torch.zeros(1, P, D), "big", traj)


def test_bad_commands_name_the_expected_shape(tiny):
    ckpt, _ = tiny
    ctl = CAMDMController(ckpt)
    ctl.reset(walker("big"))
    short = Commands.hold([1.0, 0.0], 0.0, 0, 5)
    with pytest.raises(InputError, match=r"commands.velocity must have shape \(1, N >= 9, 2\)"):
        ctl.run(short, 9)
    nan = Commands.hold([float("nan"), 0.0], 0.0, 0, 9)
    with pytest.raises(InputError, match="commands.velocity must be finite"):
        ctl.run(nan, 9)
    with pytest.raises(InputError, match=r"style indices in \[0, 1\]"):
        ctl.run(Commands.hold([1.0, 0.0], 0.0, 7, 9), 9)


@pytest.mark.parametrize(
    "value, error, words",
    [
        (-0.1, InputError, "a finite number >= 0.0, got -0.1"),
        (float("nan"), InputError, "a finite number >= 0.0, got nan"),
        ("0.1", InputTypeError, "a finite number >= 0.0, got '0.1'"),
    ],
)
def test_a_bad_replan_halflife_names_the_field(tiny, value, error, words):
    ckpt, _ = tiny
    with pytest.raises(error, match=f"ControlConfig.halflife_replan must be {re.escape(words)}"):
        CAMDMController(ckpt, ControlConfig(halflife_replan=value))


def test_a_plan_used_up_is_followed_by_one_on_the_users_trajectory(tiny, monkeypatch):
    """M >= F: HFTE has no predicted point left to extend, so the next plan's trajectory is the
    user's spring path, as without HFTE (it used to raise inside extend_trajectory)."""
    ckpt, _ = tiny
    seen = {}
    for extend in (True, False):
        ctl = CAMDMController(ckpt, ControlConfig(M=F + 3, extend=extend))
        ctl.reset(walker("small"))
        n = 2 * F + 1
        cmd = Commands.hold([0.5, 0.5], 1.0, 1, n)
        seen[extend] = ctl.run(cmd, n, torch.Generator().manual_seed(1))
        assert seen[extend].replans == [0, F, 2 * F]
    for a, b in zip(seen[True].trajectories, seen[False].trajectories, strict=True):
        assert torch.allclose(a, b)
    assert torch.equal(seen[True].frames, seen[False].frames)


def test_a_start_of_another_skeleton_is_refused(tiny):
    ckpt, _ = tiny
    ctl = CAMDMController(ckpt)
    with pytest.raises(MismatchError, match="another skeleton"):
        ctl.reset(walker("big", names=("pelvis", "torso", "thighL", "thighR")))


def test_a_checkpoint_for_another_skeleton_or_style_set_is_refused(tiny):
    ckpt, _ = tiny
    other = walker("big", names=("pelvis", "torso", "thighL", "thighR")).skeleton
    with pytest.raises(CheckpointMismatchError, match="another skeleton") as e:
        load_camdm(ckpt.paths.weights, expected_skeleton=other)
    assert "Hips" in str(e.value) and "pelvis" in str(e.value)
    with pytest.raises(CheckpointMismatchError, match="another style set") as e:
        load_camdm(ckpt.paths.weights, expected_styles=["happy", "sad"])
    assert "['big', 'small']" in str(e.value) and "['happy', 'sad']" in str(e.value)


def test_a_classifier_of_another_style_set_is_refused(tmp_path):
    from minimdm.camdm.classifier import ClassifierNetConfig, StyleClassifier, style_accuracy
    from minimdm.checkpoint import save_checkpoint

    net_ = StyleClassifier(ClassifierNetConfig(3 + 12 * J, 2, width=8, feature_dim=4))
    save_checkpoint(tmp_path, net_, {"styles": ["big", "small"], "config": {"window": 60}})
    with pytest.raises(CheckpointMismatchError, match="another style set") as e:
        load_classifier(tmp_path, expected_styles=["happy", "sad"])
    assert "['big', 'small']" in str(e.value) and "['happy', 'sad']" in str(e.value)
    ckpt = load_classifier(tmp_path, expected_styles=["big", "small"])
    with pytest.raises(InputError, match=r"frames must be world frames of shape \(B, N >= 60, D\)"):
        style_accuracy(ckpt, torch.zeros(1, 30, D), torch.zeros(1))


def test_the_camdm_command_reports_a_missing_config_in_one_line(capsys, tmp_path):
    code = main(["camdm", "train", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("minimdm camdm train: error:") and "nope.yaml" in err


# ------------------------------------------------------------------------------ shipped


def test_the_shipped_checkpoints_load_and_record_their_command():
    ckpt = minimdm.pretrained("camdm")
    assert ckpt.kind == "camdm"
    assert ckpt.metadata["command"].startswith("minimdm camdm train configs/camdm.yaml")
    assert ckpt.paths.weights.stat().st_size <= 5_000_000
    layout = CAMDMLayout.from_dict(ckpt.feature_layout)
    assert (layout.past, layout.future, len(layout.styles)) == (10, 45, 15)
    assert ckpt.schedule().T == 8
    cls = load_classifier(
        minimdm.CHECKPOINT_DIR / "camdm_classifier", expected_styles=layout.styles
    )
    assert cls.metadata["command"].startswith("minimdm camdm classifier configs/")
    assert cls.metadata["heldout_accuracy"] > 0.5


def test_mirror_adds_every_take_reflected_with_its_style():
    sides = ("Hips", "Spine", "Leg_L", "Leg_R")
    clips = [walker("big", names=sides), walker("small", names=sides, speed=0.02)]
    plain = data_from_clips(clips, tiny_config())
    mirrored = data_from_clips(clips, tiny_config(mirror=True))
    assert len(mirrored.bank) == 2 * len(plain.bank)
    assert mirrored.clip_names == plain.clip_names + [f"{n}~mirror" for n in plain.clip_names]
    assert mirrored.layout.styles == plain.layout.styles  # a reflected take keeps its style
    idx = torch.arange(len(plain.bank))
    w, s = plain.bank.batch(idx, plain.skeleton.lateral_axis)
    wm, sm = mirrored.bank.batch(idx + len(plain.bank), plain.skeleton.lateral_axis)
    assert torch.equal(s, sm)
    assert not torch.allclose(w, wm)  # the legs swap: the mirrored windows are other frames


@given(counts=st.lists(st.integers(1, 40), min_size=1, max_size=6), balance=st.floats(0, 1))
def test_style_balance_weighs_each_style_by_its_windows_to_the_minus_balance(counts, balance):
    style = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    w = window_weights(style, balance)
    if balance == 0:
        assert w is None  # uniform draws, as before the field existed
        return
    per_style = torch.zeros(len(counts), dtype=torch.float64).index_add_(0, style, w)
    expected = torch.tensor(counts, dtype=torch.float64) ** (1 - balance)
    assert torch.allclose(per_style / per_style.sum(), expected / expected.sum())


def test_a_balanced_run_draws_a_rare_style_as_often_as_a_common_one(tiny, monkeypatch, tmp_path):
    """Two styles of about 1:5 windows: drawn about 1:5 by default, 1:1 balanced."""
    from minimdm.camdm import train as camdm_train

    _, data = tiny
    short = walker("small", speed=0.02, n=data.layout.window + 20)
    skewed = data_from_clips([walker("big", n=4 * data.layout.window + 80), short], tiny_config())
    drawn = []
    make = camdm_train.make_batch

    def spy(d, idx, sigmas, generator, bank=None):
        if bank is None:  # a training batch, not the evaluation's
            drawn.append(d.bank.style[idx])
        return make(d, idx, sigmas, generator, bank)

    monkeypatch.setattr(camdm_train, "make_batch", spy)
    shares = {}
    for balance in (0.0, 1.0):
        drawn.clear()
        config = tiny_config(total_steps=40, batch_size=32, style_balance=balance)
        train_camdm(config, tmp_path / str(balance), data=skewed, progress=False)
        shares[balance] = torch.cat(drawn).float().mean().item()  # share of style 1 (small)
    counts = torch.bincount(skewed.bank.style).tolist()
    assert abs(shares[0.0] - counts[1] / sum(counts)) < 0.06
    assert abs(shares[1.0] - 0.5) < 0.06


def test_a_bad_style_balance_names_the_field():
    with pytest.raises(ValueError, match=r"style_balance must lie in \[0, 1\], got 1.5"):
        tiny_config(style_balance=1.5)


def test_a_run_saved_before_a_field_existed_resumes_when_the_field_keeps_its_default(
    tiny, tmp_path
):
    """A config field added after a run started (here ``mirror``) is missing from its saved
    config: resuming counts it as the field's default, and refuses any other value, naming it."""
    import json

    from safetensors import safe_open
    from safetensors.torch import save_file

    _, data = tiny
    config = tiny_config(total_steps=20, ckpt_interval=10)
    train_camdm(config, tmp_path, data=data, progress=False)
    state = tmp_path / "model.train.safetensors"
    with safe_open(state, "pt") as f:
        header, tensors = f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    meta = json.loads(header["minimdm"])
    del meta["config"]["mirror"]  # as a run saved before the field existed
    save_file(tensors, state, metadata={**header, "minimdm": json.dumps(meta)})
    longer = dict(total_steps=30, ckpt_interval=10)
    with pytest.raises(ValueError, match=r"mirror: False vs True"):
        train_camdm(tiny_config(**longer, mirror=True), tmp_path, data=data, progress=False)
    ckpt = train_camdm(tiny_config(**longer), tmp_path, data=data, progress=False)
    assert ckpt.step == 30
