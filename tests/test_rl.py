"""Chapter 7: the residual hook (eq. 7), the tasks (eq. 8), the environments, PPO and policies."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import minimdm
from minimdm.amdm.sampling import Sampler
from minimdm.checkpoint import CheckpointMismatchError
from minimdm.diffusion import DDIMStep, NoiseSchedule, reverse_chain
from minimdm.motion import metrics
from minimdm.motion.features import decode
from minimdm.rl import (
    Characters,
    JoystickTask,
    PathTask,
    ResidualSchedule,
    SteeringEnv,
    SteeringVecEnv,
    TargetTask,
    joystick_reward,
    load_steering,
    residual_hook,
)
from minimdm.rl.env import LatentSteerer, ResidualSteerer, make_steerer
from minimdm.rl.train import RLConfig, build_env, corpus_starts, make_config_steerer

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def base():
    return minimdm.pretrained("amdm")  # the base model the shipped policies steer


@pytest.fixture(scope="module")
def starts(base):
    return corpus_starts(base)[::50]  # every 50th training frame: enough variety, fast


# -- eq. 7: the residual hook ---------------------------------------------------------------


def test_linear_and_cosine_weights_anneal_towards_the_last_steps():
    lin = ResidualSchedule(20, (19, 15, 11, 7), "linear", 2.0).weights()
    assert torch.allclose(lin, torch.tensor([2.0, 1.5, 1.0, 0.5]))
    cos = ResidualSchedule.top(20, 8, "cosine").weights()
    assert cos[0] == pytest.approx(1.0) and (cos[1:] < cos[:-1]).all() and (cos > 0).all()
    assert torch.equal(ResidualSchedule.top(20, 3, "none").weights(), torch.ones(3))


def test_bad_schedules_are_refused():
    with pytest.raises(ValueError, match="strictly decreasing"):
        ResidualSchedule(20, (3, 5))
    with pytest.raises(ValueError, match=r"\[0, T-1=19\]"):
        ResidualSchedule(20, (20, 3))
    with pytest.raises(ValueError, match="anneal"):
        ResidualSchedule(20, (5,), "exp")


class _Zero(torch.nn.Module):
    def forward(self, x, t, cond):
        return torch.zeros_like(x)


@given(
    levels=st.lists(st.integers(0, 9), min_size=1, max_size=10, unique=True),
    n_feat=st.integers(1, 6),
    seed=st.integers(0, 1000),
)
@settings(max_examples=30, deadline=None)
def test_residuals_land_at_exactly_the_chosen_steps_with_weight_w(levels, n_feat, seed):
    """Recorders before and after the hook in a real reverse chain: the hook adds w^t a^t on the
    chosen features after the steps from the chosen levels, and nothing anywhere else."""
    g = torch.Generator().manual_seed(seed)
    T, B, D = 10, 3, 6
    levels = tuple(sorted(levels, reverse=True))
    sched = ResidualSchedule(T, levels, "linear", 1.5)
    feats = sorted(torch.randperm(D, generator=g)[:n_feat].tolist())
    actions = torch.randn(B, len(levels), n_feat, generator=g)
    chain = list(range(T - 1, -1, -1))
    seen = {}

    def before(t, x, x0):
        seen[t] = [x.clone()]
        return x

    def after(t, x, x0):
        seen[t].append(x.clone())
        return x

    rule = DDIMStep(_Zero(), NoiseSchedule("cosine", T), "eps", eta=1.0)
    hook = residual_hook(sched, actions, chain, feats)
    x = torch.randn(B, D, generator=g)
    reverse_chain(rule, x, chain, None, g, [before, hook, after])
    w = sched.weights()
    for t in chain:
        t_next = t - 1
        delta = seen[t_next][1] - seen[t_next][0]
        expect = torch.zeros(B, D)
        if t in levels:
            k = levels.index(t)
            expect[:, feats] = w[k] * actions[:, k]
        tol = 1e-6 * (1 + seen[t_next][0].abs().max())  # float32 rounding of x + delta - x
        assert torch.allclose(delta, expect, atol=float(tol)), (t, levels)


def test_residual_hook_refuses_bad_actions_and_skipped_levels():
    sched = ResidualSchedule(10, (9, 8))
    chain = list(range(9, -1, -1))
    with pytest.raises(ValueError, match=r"actions must have shape \(B, 2, 3\)"):
        residual_hook(sched, torch.zeros(4, 5), chain, [0, 1, 2])
    with pytest.raises(ValueError, match="finite"):
        residual_hook(sched, torch.full((4, 2, 3), float("nan")), chain, [0, 1, 2])
    with pytest.raises(ValueError, match="never steps from the perturbed levels"):
        residual_hook(sched, torch.zeros(4, 2, 3), [9, 5, 0], [0, 1, 2])


# -- eq. 8 and the tasks --------------------------------------------------------------------


def test_joystick_reward_eq8_on_hand_made_values():
    h = torch.tensor([0.0, 0.0, math.pi, 1.0, 0.5])
    v = torch.tensor([1.0, 2.0, 1.0, 1.5, 0.0])
    gh = torch.tensor([0.0, 0.0, 0.0, 1.0 + math.pi / 2, 0.5])
    gv = torch.tensor([1.0, 1.0, 1.0, 1.0, 3.0])
    r = joystick_reward(h, v, gh, gv)
    expect = torch.tensor(
        [1.0, math.exp(-1), math.exp(-2), math.exp(-1) * math.exp(-0.5), math.exp(-3)]
    )
    assert torch.allclose(r, expect, atol=1e-6)


def _chars(xy, heading=0.0):
    ch = Characters.zeros(len(xy))
    ch.xy = torch.as_tensor(xy, dtype=torch.float32)
    ch.heading = torch.full((len(xy),), float(heading))
    return ch


def test_target_is_reached_within_15cm_even_between_frames_and_then_moves():
    task = TargetTask()
    task.setup(3, torch.Generator().manual_seed(0))
    ch = _chars([[0.0, 0.0]] * 3)
    task.set_targets(torch.tensor([[1.0, 0.0], [1.0, 0.2], [1.0, 0.1]]))
    prev = torch.tensor([[0.9, 0.0], [0.9, 0.0], [0.8, 0.0]])
    ch.xy = torch.tensor([[0.95, 0.0], [0.95, 0.0], [1.2, 0.0]])  # row 2 walks past its target
    reward, term, info = task.step(ch, prev)
    assert info["hit"].tolist() == [True, False, True]
    assert not term.any()
    assert (reward[[0, 2]] > task.bonus).all() and reward[1] < task.bonus
    moved = (task.target - torch.tensor([[1.0, 0.0], [1.0, 0.2], [1.0, 0.1]])).norm(dim=1)
    assert moved[0] > 0 and moved[1] == 0 and moved[2] > 0
    d = (task.target[[0, 2]] - ch.xy[[0, 2]]).norm(dim=1)
    assert ((d >= task.min_distance - 1e-5) & (d <= task.region + 1e-5)).all()


def test_a_queue_of_targets_appears_in_order_then_random_ones():
    task = TargetTask()
    task.setup(2, torch.Generator().manual_seed(0))
    ch = _chars([[0.0, 0.0]] * 2)
    task.reset(torch.arange(2), ch)
    queue = torch.tensor([[[1.0, 0.0], [2.0, 0.0]], [[0.0, 1.0], [0.0, 2.0]]])
    task.set_targets(queue)
    assert torch.equal(task.target, queue[:, 0])
    ch.xy = queue[:, 0].clone()
    task.step(ch, ch.xy)
    assert torch.equal(task.target, queue[:, 1])
    ch.xy = queue[:, 1].clone()
    task.step(ch, ch.xy)
    d = (task.target - ch.xy).norm(dim=1)
    assert ((d >= task.min_distance - 1e-5) & (d <= task.region + 1e-5)).all()


@settings(max_examples=30, deadline=None)
@given(speed=st.floats(0.0, 4.0), cap=st.floats(0.5, 3.0))
def test_target_progress_pays_only_up_to_max_progress(speed, cap):
    """Walking straight at a far target at ``speed`` m/s: without max_progress the reward
    grows with the speed; with it the progress term grows up to cap and falls beyond it, as
    fast as it grew (walking at cap pays best)."""
    rewards = {}
    for limit in (None, cap):
        task = TargetTask(max_progress=limit)
        task.setup(1, torch.Generator().manual_seed(0))
        task.set_targets(torch.tensor([[8.0, 0.0]]))
        prev = torch.zeros(1, 2)
        ch = _chars([[speed / 30, 0.0]])  # one frame at 30 fps, facing the target
        reward, _, _ = task.step(ch, prev)
        distance = task.w_distance * math.exp(-0.5 * (8.0 - speed / 30))
        rewards[limit] = float(reward[0]) - distance
    assert rewards[None] == pytest.approx(speed, rel=1e-3, abs=1e-3)
    assert rewards[cap] == pytest.approx(cap - abs(speed - cap), rel=1e-3, abs=1e-3)
    with pytest.raises(ValueError, match="max_progress"):
        TargetTask(max_progress=0.0)


def test_target_observation_is_in_the_heading_frame():
    task = TargetTask()
    task.setup(1, torch.Generator())
    task.set_targets(torch.tensor([[0.0, 5.0]]))
    obs = task.observe(_chars([[0.0, 0.0]], heading=math.pi / 2))  # facing +y: target ahead
    assert torch.allclose(obs, torch.tensor([[0.5, 0.0, 1.0, 0.0]]), atol=1e-6)


def test_joystick_redraws_direction_every_120_and_speed_every_240_frames():
    task = JoystickTask()
    task.setup(1, torch.Generator().manual_seed(1))
    ch = _chars([[0.0, 0.0]])
    task.reset(torch.tensor([0]), ch)
    h0, v0 = task.goal_heading.clone(), task.goal_speed.clone()
    changes = []
    for f in range(1, 481):
        ch.frame = torch.tensor([f])
        task.step(ch, ch.xy)
        changes.append((bool(task.goal_heading != h0), bool(task.goal_speed != v0)))
        h0, v0 = task.goal_heading.clone(), task.goal_speed.clone()
    heading_changes = [f for f, (h, _) in enumerate(changes, 1) if h]
    speed_changes = [f for f, (_, v) in enumerate(changes, 1) if v]
    assert heading_changes == [120, 240, 360, 480]
    assert speed_changes == [240, 480]


def test_joystick_pays_for_velocity_along_the_command_not_for_walking_backwards():
    task = JoystickTask()
    task.setup(2, torch.Generator())
    task.command(torch.tensor([0.0, 0.0]), torch.tensor([1.5, 1.5]))
    ch = _chars([[0.0, 0.0]] * 2)  # both face the command (+x)
    ch.velocity = torch.tensor([[1.5, 0.0], [-1.5, 0.0]])  # forwards, backwards
    reward, _, info = task.step(ch, ch.xy)
    assert reward[0] == pytest.approx(1.0) and reward[1] == pytest.approx(math.exp(-3.0))
    assert torch.allclose(info["speed_error"], torch.tensor([0.0, -3.0]))


def test_preset_joystick_commands_drive_every_frame():
    task = JoystickTask()
    task.setup(2, torch.Generator())
    heading = torch.tensor([[0.0, 1.0, 2.0], [0.5, 0.5, -1.0]])
    speed = torch.tensor([[1.0, 1.5, 2.0], [0.5, 0.6, 0.7]])
    task.preset(heading, speed)
    ch = _chars([[0.0, 0.0]] * 2)
    seen = []
    for f in range(1, 5):
        seen.append(task.goal_heading.clone())
        ch.frame = torch.tensor([f, f])
        task.step(ch, ch.xy)
    assert torch.equal(torch.stack(seen, 1), heading[:, [0, 1, 2, 2]])
    assert torch.equal(task.goal_speed, speed[:, 2])
    with pytest.raises(ValueError, match=r"shape \(2, P\)"):
        task.preset(heading[:1], speed[:1])


def test_joystick_speeds_outside_the_corpus_range_are_accepted_but_reported():
    task = JoystickTask(corpus_speed=(0.0, 4.5))
    task.setup(2, torch.Generator())
    task.command(torch.tensor([0.0, 0.0]), torch.tensor([2.0, 9.0]))
    _, _, info = task.step(_chars([[0.0, 0.0]] * 2), torch.zeros(2, 2))
    assert info["out_of_range"].tolist() == [False, True]
    assert task.goal_speed.tolist() == [2.0, 9.0]


def test_path_episode_ends_when_the_character_leaves_the_path():
    task = PathTask(max_deviation=1.0)
    task.setup(2, torch.Generator().manual_seed(0))
    ch = _chars([[0.0, 0.0]] * 2)
    task.reset(torch.arange(2), ch)
    assert torch.allclose(task.path[:, 0], torch.zeros(2, 2))
    ch.frame = torch.tensor([30, 30])
    ch.xy = task.path[:, 30] + torch.tensor([[0.0, 0.0], [0.0, 1.5]])
    ahead = task.path[:, 35] - task.path[:, 30]  # face along the path
    ch.heading = torch.atan2(ahead[:, 1], ahead[:, 0])
    reward, term, info = task.step(ch, ch.xy)
    assert term.tolist() == [False, True]
    assert torch.allclose(info["deviation"], torch.tensor([0.0, 1.5]), atol=1e-5)
    assert reward[0] == pytest.approx(1.0) and reward[1] == pytest.approx(math.exp(-3))
    ch.heading = ch.heading + math.pi  # backwards along the path: the facing factor is 1 - w
    assert task.step(ch, ch.xy)[0][0] == pytest.approx(1.0 - task.w_facing, abs=1e-5)


# -- the environments -----------------------------------------------------------------------


@pytest.mark.parametrize("task", [TargetTask, JoystickTask, PathTask])
def test_single_character_env_passes_gymnasiums_checker(base, starts, task):
    from gymnasium.utils.env_checker import check_env

    cm = Sampler.load(base)
    env = SteeringEnv(cm, ResidualSteerer(cm, ResidualSchedule.top(20, 4), "root"), task(), starts)
    with pytest.warns(UserWarning, match="infinity"):  # unbounded frames: Box(-inf, inf)
        check_env(env, skip_render_check=True)


def test_one_batched_model_call_per_level_steps_every_character(base, starts):
    cm = Sampler.load(base)
    env = SteeringVecEnv(
        cm, ResidualSteerer(cm, ResidualSchedule.top(20, 5), "all"), TargetTask(), starts, 7
    )
    calls = []
    handle = cm.net.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    try:
        env.reset(seed=0)
        env.step(np.zeros((7, env.single_action_space.shape[0]), np.float32))
    finally:
        handle.remove()
    assert calls == [7] * 20


def test_a_root_observing_env_shows_the_root_velocity_and_yaw_rate_then_the_task(base, starts):
    cm = Sampler.load(base)
    steer = ResidualSteerer(cm, ResidualSchedule.top(20, 2, tied=True), "root")
    env = SteeringVecEnv(cm, steer, JoystickTask(), starts, 5, seed=0, observe="root")
    obs, _ = env.reset(seed=0)
    lay = cm.layout
    seen = [lay.root_vel.start, lay.root_vel.start + 1, lay.yaw_rate.start]
    assert obs.shape == (5, 3 + 4) == env.observation_space.shape
    assert np.allclose(obs[:, :3], env.x[:, seen].numpy())
    assert np.allclose(obs[:, 3:], env.task.observe(env.ch).numpy())
    obs, *_ = env.step(np.zeros((5, 3), np.float32))
    assert np.allclose(obs[:, :3], env.x[:, seen].numpy())


def test_vec_env_restarts_finished_episodes_in_the_same_step(base, starts):
    cm = Sampler.load(base)
    steer = ResidualSteerer(cm, ResidualSchedule.top(20, 2), "root")
    env = SteeringVecEnv(cm, steer, JoystickTask(max_frames=3), starts, 4, seed=0)
    env.reset(seed=0)
    a = np.zeros((4, 6), np.float32)
    for _ in range(2):
        *_, trunc, infos = env.step(a)
        assert not trunc.any() and "final_obs" not in infos
    obs, _, term, trunc, infos = env.step(a)
    assert trunc.all() and not term.any() and infos["_final_obs"].all()
    assert (infos["episode_length"] == 3).all()
    assert (env.ch.frame == 0).all() and torch.allclose(env.ch.xy, torch.zeros(4, 2))
    assert not np.allclose(obs, infos["final_obs"])


def test_a_spin_ends_the_episode_when_max_turn_rate_is_set(base, starts):
    """The yaw rate's half-second average is watched: pushed to turn hard every frame, the
    characters pass 200 degrees per second within a few frames and their episodes end
    (terminated, and restarted in the same step); without max_turn_rate they never do."""
    cm = Sampler.load(base)
    steer = ResidualSteerer(cm, ResidualSchedule.top(20, 10, tied=True), "root")
    ends = {}
    for limit in (None, 200.0):
        env = SteeringVecEnv(cm, steer, JoystickTask(max_frames=200), starts, 4, seed=0,
                             max_turn_rate=limit)  # fmt: skip
        env.reset(seed=0)
        a = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (4, 1))  # full yaw, every frame
        ends[limit] = []
        for f in range(60):
            turn = env.turn.clone()
            _, _, term, _, infos = env.step(a)
            if term.any():
                i = int(np.flatnonzero(term)[0])
                assert "spun" in infos and infos["spun"][i] and infos["_final_obs"][i]
                assert env.turn[i] == 0 and env.ch.frame[i] == 0  # restarted at once
                ends[limit].append(f)
            else:  # the average moves a 15th of the way to the new frame's yaw rate
                yaw = env._feats(env.x)[:, cm.layout.yaw_rate.start]
                torch.testing.assert_close(env.turn, turn + (yaw - turn) / 15)
    assert ends[None] == [] and 0 < len(ends[200.0]) and ends[200.0][0] < 30, ends
    with pytest.raises(ValueError, match="max_turn_rate"):
        SteeringVecEnv(cm, steer, JoystickTask(), starts, 4, max_turn_rate=0.0)


@settings(max_examples=40, deadline=None)
@given(
    rate=st.floats(-400.0, 400.0),  # the current frame's yaw rate, degrees per second
    action=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
)
def test_the_turn_governor_fades_only_a_yaw_push_that_turns_faster(base, rate, action):
    """max_yaw_rate: a yaw residual in the direction of the turn passes whole below 3/4 of the
    limit and falls linearly to nothing at the limit and past it; a push against the turn, and
    the velocity residuals, pass unchanged."""
    cm, limit = Sampler.load(base), 120.0
    steer = ResidualSteerer(cm, ResidualSchedule.top(20, 10, tied=True), "root", limit)
    feats = cm.denormalize(torch.zeros(1, cm.dim))
    feats[0, cm.layout.yaw_rate.start] = math.radians(rate) / cm.fps
    a = torch.tensor([action], dtype=torch.float32)
    out = steer.governed(cm.normalize(feats), a)
    torch.testing.assert_close(out[:, :2], a[:, :2])
    yaw = float(a[0, 2])
    along = (1.0 if yaw > 0 else -1.0 if yaw < 0 else 0.0) * rate
    room = min(max((limit - along) / (limit / 4), 0.0), 1.0)
    assert math.isclose(float(out[0, 2]), yaw * room, rel_tol=1e-4, abs_tol=1e-5)
    if abs(rate) < 0.75 * limit or along < 0:  # within the corpus's turning, or against it
        assert math.isclose(float(out[0, 2]), yaw, rel_tol=1e-4, abs_tol=1e-5)
    if along >= limit:  # turning this fast already: no further push that way
        assert float(out[0, 2]) == 0.0


def test_the_turn_governor_keeps_a_held_yaw_push_from_spinning_the_character(base):
    """A full yaw push held for two seconds: without the governor every character turns
    faster and faster (the base model keeps a turn going by itself, past 500 degrees per
    second); with max_yaw_rate 120 most stay within the corpus's turning (their half-second
    average under 240 degrees per second, about the corpus's 99th percentile: the model may
    still carry a turn on past the limit by itself, so not all) and each still turns round."""
    cm = Sampler.load(base)
    starts = cm.normalize(corpus_starts(base)[::3000][:8])
    sched = ResidualSchedule.top(20, 10, tied=True, scale=2.0)
    turned, fastest = {}, {}
    for limit in (None, 120.0):
        steer = ResidualSteerer(cm, sched, "root", limit)
        assert make_steerer(cm, steer.to_dict()).max_yaw_rate == limit  # a checkpoint keeps it
        x, g, rates = starts, torch.Generator().manual_seed(0), []
        a = torch.tensor([[0.0, 0.0, 1.0]]).expand(len(starts), 3)
        for _ in range(60):
            x = steer(x, a, g)
            rates.append(cm.denormalize(x)[:, cm.layout.yaw_rate.start] * cm.fps)
        deg_s = torch.rad2deg(torch.stack(rates, 1))  # (8, 60)
        turned[limit] = float(deg_s.mean(1).min()) * 2  # degrees in 2 s, the least of the 8
        fastest[limit] = torch.nn.functional.avg_pool1d(deg_s[:, None], 15, 1)[:, 0].amax(1)
    assert (fastest[None] > 500).all() and fastest[120.0].median() < 240, fastest
    assert (fastest[120.0] < fastest[None]).all(), fastest
    assert turned[120.0] > 120, turned
    with pytest.raises(ValueError, match="max_yaw_rate"):
        ResidualSteerer(cm, sched, "root", 0.0)
    with pytest.raises(ValueError, match="max_yaw_rate"):
        RLConfig(max_yaw_rate=-5.0)


def test_env_refuses_actions_of_the_wrong_shape_or_not_finite(base, starts):
    env = build_env(
        RLConfig(task="target", num_envs=3, batch_size=96, features="root", n_levels=4), base
    )
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must have shape \(3, 12\)"):
        env.step(np.zeros((3, 13), np.float32))
    bad = np.zeros((3, 12), np.float32)
    bad[1, 4] = np.inf
    with pytest.raises(ValueError, match="environment 1 holds NaN/Inf"):
        env.step(bad)


def test_motion_penalty_is_the_libraries_bone_error_and_foot_sliding_of_each_new_frame(
    base, starts
):
    """The env's per-frame quality equals metrics.bone_length_error / foot_sliding on the
    decoded rollout, and the reward pays ``motion_penalty`` per cm of their sum."""
    cfg = RLConfig(task="joystick", num_envs=2, batch_size=64, n_levels=4, tied=True)
    plain = build_env(cfg, base)
    env = build_env(RLConfig(**{**cfg.__dict__, "motion_penalty": 0.5}), base)
    g = np.random.default_rng(0)
    for e in (plain, env):
        e.reset(seed=3)
    frames, infos = [], []
    for _ in range(6):
        a = (0.5 * g.standard_normal((2, env.single_action_space.shape[0]))).astype(np.float32)
        _, r0, *_ = plain.step(a)
        _, r, _, _, info = env.step(a)
        frames.append(env.cm.denormalize(env.x).double())
        infos.append(info)
        assert np.allclose(r, r0 - 0.5 * (info["bone_cm"] + info["slide_cm"]), atol=1e-5)
    sk = env.cm.skeleton
    origin = {"xy": torch.zeros(2, 2), "heading": torch.zeros(2)}  # where the env starts
    pos = decode(torch.stack(frames, 1), origin)  # (2, 6, J, 3)
    ref = metrics.skeleton_bone_lengths(sk.offsets, sk.parents)
    z0 = env.quality.z0.double()
    for i in range(2):
        for k in range(1, 6):
            bone = metrics.bone_length_error(pos[i, k : k + 1], sk.parents, ref)
            slide = metrics.foot_sliding(pos[i, k - 1 : k + 1], sk.foot_indices, foot_offset=z0)
            assert infos[k]["bone_cm"][i] == pytest.approx(bone, rel=1e-4, abs=1e-4)
            assert infos[k]["slide_cm"][i] == pytest.approx(slide, rel=1e-4, abs=1e-4)
    assert np.mean([i["bone_cm"] for i in infos]) > 1.0  # pushed frames leave the data


def test_latent_steerer_decodes_the_action_as_mvae_latent():
    mvae = minimdm.pretrained("mvae")
    cm = Sampler.load(mvae)
    s = LatentSteerer(cm, scale=2.0)
    cond = torch.randn(5, cm.dim)
    a = torch.rand(5, s.action_dim) * 2 - 1
    assert torch.allclose(s(cond, a, torch.Generator()), cm.net.decode(2 * a, cond))
    with pytest.raises(ValueError, match="max_yaw_rate governs an A-MDM residual"):
        make_config_steerer(cm, RLConfig(base="mvae", max_yaw_rate=120.0))


# -- PPO and the policy checkpoint ----------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_policy(base, tmp_path_factory):
    """A short PPO run (about 100,000 frames, 30 s) on target reaching, on a 4-step DDIM chain
    of the base model with residuals on its two noisiest steps."""
    from minimdm.rl.train import train_policy

    out = tmp_path_factory.mktemp("rl") / "target"
    config = RLConfig(
        base="amdm",
        task="target",
        task_options={"max_frames": 150},
        steps=4,
        levels=[19, 13],
        tied=True,
        features="root",
        residual_scale=2.0,
        num_envs=32,
        n_steps=16,
        batch_size=256,
        lr=1e-3,
        total_steps=32 * 16 * 200,
        seed=0,
    )
    return config, train_policy(config, out, progress=False, base=base), out


def test_tiny_ppo_run_beats_random_actions(tiny_policy):
    from minimdm.rl.rollout import steer

    config, result, out = tiny_policy
    lines = (out / "log.jsonl").read_text().splitlines()
    assert len(lines) == len(result.history) == 200
    steering = load_steering(out)
    kw = dict(n_frames=150, num_envs=32, seed=123)
    trained = steer(steering, **kw).reward.mean()
    steering.policy.log_std.fill_(0.0)
    with torch.no_grad():  # random actions: zero mean, unit std, clipped to [-1, 1]
        steering.policy.head.weight.zero_()
        steering.policy.head.bias.zero_()
    random = steer(steering, deterministic=False, **kw).reward.mean()
    assert trained > random + 0.1, (float(trained), float(random))


def test_policy_checkpoint_acts_like_the_sb3_actor_and_is_not_pickled(base, tiny_policy):
    config, result, out = tiny_policy
    assert sorted(p.name for p in out.iterdir()) == ["log.jsonl", "model.json", "model.safetensors"]
    meta = result.checkpoint.metadata
    assert meta["base"]["name"] == "amdm" and meta["task"]["name"] == "target"
    assert meta["env_steps"] == config.total_steps
    steering = load_steering(out, task="target")
    assert steering.steerer.schedule.levels == (19, 13) and steering.cm.settings.steps == 4
    obs = torch.randn(9, steering.policy.obs_dim)
    sb3_actions, _ = result.model.predict(obs.numpy(), deterministic=True)
    assert np.allclose(steering.policy.act(obs).numpy(), sb3_actions, atol=1e-6)


def test_policy_for_another_base_model_or_task_is_refused(tiny_policy):
    _, _, out = tiny_policy
    with pytest.raises(CheckpointMismatchError, match=r"trained on the base model 'amdm'.*'mse'"):
        load_steering(out, base="mse")
    with pytest.raises(CheckpointMismatchError, match="task 'target', not 'joystick'"):
        load_steering(out, task="joystick")


def test_a_tied_residual_is_the_same_vector_at_every_chosen_level_weighted_by_w():
    sched = ResidualSchedule(10, (9, 7, 5), "linear", 3.0, tied=True)
    a = torch.tensor([[1.0, -2.0]])
    hook = residual_hook(sched, a, range(9, -1, -1), [0, 4])
    x = torch.zeros(1, 5)
    added = {t: hook(t - 1, x, x) for t in range(10)}
    for t, w in zip((9, 7, 5), (3.0, 2.0, 1.0), strict=True):
        assert torch.allclose(added[t], torch.tensor([[w, 0, 0, 0, -2 * w]]))
    assert all(torch.equal(added[t], x) for t in (8, 6, 4, 3, 2, 1, 0))


def test_root_residuals_push_only_the_roots_velocity_and_yaw_rate(base):
    names = ["forward", "left", "yaw"]
    cm = Sampler.load(base)
    lay = cm.layout
    steer = ResidualSteerer(cm, ResidualSchedule.top(20, 3, tied=True), "root")
    dims = {"forward": lay.root_vel.start, "left": lay.root_vel.start + 1}
    dims["yaw"] = lay.yaw_rate.start
    assert steer.action_dim == len(names)
    hook = residual_hook(steer.schedule, torch.ones(1, len(names)), steer.chain, steer.idx)
    x = torch.zeros(1, cm.dim)
    pushed = hook(18, x, x)  # after the step from the noisiest level 19: w = scale * 1
    assert pushed.nonzero()[:, 1].tolist() == sorted(dims[n] for n in names)


@pytest.mark.parametrize("name", ["rl_target", "rl_joystick", "rl_path", "rl_target_mvae"])
def test_shipped_policies_load_with_their_base_model_and_record_their_command(name):
    s = load_steering(name)
    meta = s.checkpoint.metadata
    assert meta["command"].startswith(f"minimdm rl configs/{name}.yaml")
    assert meta["train_seconds"] < 60 * 60  # issue 31's limit for one run on 2 cores
    assert s.checkpoint.paths.weights.stat().st_size < 5 * 2**20
    obs = torch.zeros(3, s.policy.obs_dim)
    assert s.policy.act(obs).shape == (3, s.steerer.action_dim)


def test_residuals_on_a_delta_model_are_in_the_frames_units():
    """A delta model's chain denoises the change z = (x - x_prev) / k; the steerer divides the
    residuals by k, so that a residual at the last step moves the next frame by w * a standard
    deviations of the normalized feature, as it does for a model of the frame."""
    cm = Sampler.load(minimdm.pretrained("amdm"))
    assert cm.net.is_delta
    steer = ResidualSteerer(cm, ResidualSchedule(cm.schedule.T, (0,), "none", 0.5), "root")
    cond = cm.normalize(corpus_starts(minimdm.pretrained("amdm"))[::2000][:4])
    a = torch.tensor([[1.0, -0.5, 0.25]]).expand(len(cond), 3)
    free = steer(cond, torch.zeros_like(a), torch.Generator().manual_seed(0))
    pushed = steer(cond, a, torch.Generator().manual_seed(0))
    torch.testing.assert_close(
        pushed[:, steer.idx] - free[:, steer.idx], 0.5 * a, atol=1e-4, rtol=0
    )
    others = [i for i in range(cm.dim) if i not in steer.idx]
    torch.testing.assert_close(pushed[:, others], free[:, others])
    with pytest.raises(ValueError, match="units must hold 3 positive"):
        residual_hook(steer.schedule, a, steer.chain, steer.idx, torch.ones(2))
