"""The DeepMimic clips: loading, 30 Hz resampling, loop unrolling, the z-up world, bad input."""

import json
import math
import sys
import time

import numpy as np
import pytest
import torch

from minimdm.motion.data import (
    CLIP_NAMES,
    Clip,
    MotionDataset,
    load_clips,
    load_deepmimic,
    resample_clip,
)
from minimdm.motion.skeleton import heading_angle, humanoid_skeleton, pybullet_data_path

MOTIONS = pybullet_data_path() / "data" / "motions"


def source_file(name: str):
    return MOTIONS / (f"{name}.txt" if name.startswith("walker/") else f"humanoid3d_{name}.txt")


@pytest.fixture(scope="module")
def clips() -> MotionDataset:
    return load_clips()


def _seconds(fn, repeats: int = 3) -> float:
    """The fastest of a few runs: a busy machine slows a run down, never speeds it up."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def test_all_20_clips_load_fast_at_30_hz(clips):
    # Fast: loading (parsing, forward kinematics, resampling to 30 Hz) costs at most a few times
    # reading the JSON sources, measured in the same run so that a busy machine slows both alike.
    # About 4 times here; the bound leaves a factor of 10.
    load = _seconds(load_clips)
    read = _seconds(lambda: [json.loads(source_file(n).read_text()) for n in CLIP_NAMES])
    assert load < 40 * read, f"load_clips took {load:.2f} s, reading the sources {read:.3f} s"
    assert clips.names == CLIP_NAMES and len(clips) == 20
    for c in clips:
        frames = json.loads(source_file(c.name).read_text())["Frames"]
        src_duration = sum(f[0] for f in frames[:-1])
        assert c.fps == 30 and c.skeleton.names == humanoid_skeleton().names
        assert c.positions.shape == (c.n_frames, 15, 3) and c.local_rot.shape == (c.n_frames, 15, 4)
        assert abs(c.duration - src_duration) < 1 / 30, c.name
        if abs(frames[0][0] - 1 / 30) < 1e-4:  # a 30 Hz source keeps its frames
            assert c.n_frames == len(frames), c.name
    assert clips["spin"].n_frames == 133 and clips["backflip"].n_frames == 53  # 24 Hz and 16 Hz


def test_resampling_60_to_30_keeps_positions(clips):
    c60 = load_clips(fps=60, names=["jump"])["jump"]
    c30 = clips["jump"]
    # Every other 60 Hz frame is a 30 Hz frame; they must agree exactly.
    assert np.abs(c60.positions[::2][: c30.n_frames] - c30.positions).max() < 1e-5
    assert np.abs(resample_clip(c60, 30).positions - c30.positions).max() < 1e-5
    # A 30 Hz frame between two 60 Hz key frames lies between them (slerp, no overshoot).
    c45 = resample_clip(c60, 45)
    k = np.arange(1, c45.n_frames - 1, 3)  # 45 Hz frame 3m+1 sits at 60 Hz frame 4m+1.33
    lo, hi = c60.positions[(k * 4) // 3], c60.positions[(k * 4) // 3 + 1]
    dist = np.linalg.norm(c45.positions[k] - lo, axis=-1)
    assert (dist <= np.linalg.norm(hi - lo, axis=-1) + 2e-3).all()


@pytest.mark.parametrize("name, src_fps, every", [("spin", 24, (4, 5)), ("backflip", 16, (8, 15))])
def test_upsampling_keeps_the_source_frames(clips, name, src_fps, every):
    """24 Hz and 16 Hz sources: 30 Hz frames at the source's own times reproduce it exactly."""
    src = load_clips(fps=src_fps, names=[name])[name]  # the source rate: no interpolation
    k_src, k_30 = every  # every 4th 24 Hz frame is every 5th 30 Hz frame (1/6 s apart)
    n = min(len(src.positions[::k_src]), len(clips[name].positions[::k_30]))
    assert n >= 4  # the backflip's 16 Hz and 30 Hz frames meet every 0.5 s only
    diff = clips[name].positions[::k_30][:n] - src.positions[::k_src][:n]
    assert np.abs(diff).max() < 1e-5


@pytest.mark.parametrize("name", ["walk", "run", "walker/turn_left0", "dance_a"])
def test_looping_unroll_is_continuous_and_keeps_moving(clips, name):
    one = clips[name]
    long = load_clips(loop_frames=300, names=[name])[name]
    assert long.n_frames == 300 and one.loop
    step = np.linalg.norm(np.diff(long.positions, axis=0), axis=-1).max(-1)  # (299,) worst joint
    frames = json.loads(source_file(name).read_text())["Frames"]
    period = round(sum(f[0] for f in frames[:-1]) * 30, 2)  # 30 Hz frames a cycle (dance_a 48.5)
    seams = [math.floor(k * period) - 1 for k in range(1, int(300 // period))]
    typical = np.linalg.norm(np.diff(one.positions, axis=0), axis=-1).max(-1)
    assert step[seams].max() <= 1.2 * typical.max(), "jump at the loop seam"
    assert step.max() <= 1.3 * typical.max()
    if period != int(period):
        return
    # Each cycle moves the root by the same planar distance.
    period = int(period)
    root = long.root_pos[:, :2]
    cycle = np.linalg.norm(one.root_pos[-1, :2] - one.root_pos[0, :2])
    for k in range(1, 300 // period):
        d = np.linalg.norm(root[k * period] - root[(k - 1) * period])
        assert d == pytest.approx(cycle, rel=1e-3, abs=1e-3)


def test_unrolled_turn_keeps_turning(clips):
    one = clips["walker/turn_left0"]
    long = load_clips(loop_frames=37 * 6 + 1, names=["walker/turn_left0"])["walker/turn_left0"]
    _, r1 = one.fk()
    _, rl = long.fk()
    turn = float(heading_angle(r1[-1, 0]) - heading_angle(r1[0, 0]))
    h = np.unwrap(heading_angle(rl[:, 0]).numpy())
    assert math.degrees(turn) > 20  # a left turn
    assert h[-1] - h[0] == pytest.approx(6 * turn, abs=1e-3)


def test_z_up_world(clips):
    sk = clips.skeleton
    for c in clips:
        feet = c.positions[:, sk.foot_indices, 2]
        assert -0.02 < feet.min() < 0.1, c.name  # ankles touch the ground at some point
    for name in ["walk", "run", "walker/0walk_forward", "punch", "jump"]:
        p = clips[name].positions
        assert (p[:, sk.index("neck"), 2] > p[:, sk.index("root"), 2] + 0.3).all(), name
        assert (p[:, sk.index("root"), 2] > 0.4).all()  # the jump crouches to ~0.5 m
    walk = clips["walk"].positions
    travel = walk[-1, 0] - walk[0, 0]
    assert travel[0] > 1.0 and abs(travel[1]) < 0.1 and abs(travel[2]) < 0.01  # walks along +x
    left = walk[:, sk.index("left_hip"), 1] - walk[:, sk.index("right_hip"), 1]
    assert (left > 0.1).all()  # +y is the character's left


def test_train_test_split_by_segments(clips):
    train, test = clips.train_test_split(0.2)
    for c, a, b in zip(clips, train, test, strict=True):
        assert a.n_frames + b.n_frames == c.n_frames and a.name == b.name == c.name
        assert b.n_frames == round(0.2 * c.n_frames)
        assert np.array_equal(np.concatenate([a.positions, b.positions]), c.positions)


def test_missing_pybullet_names_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "pybullet_data", None)
    with pytest.raises(ImportError, match="pip install pybullet"):
        load_clips()


def edited_walk(tmp_path, edit):
    data = json.loads(source_file("walk").read_text())
    edit(data["Frames"])
    path = tmp_path / "walk.txt"
    path.write_text(json.dumps(data))
    return path


def test_bad_rotations_name_the_frame(tmp_path):
    def nan(frames):
        frames[7][9] = float("nan")  # chest quaternion

    with pytest.raises(ValueError, match="frame 7"):
        load_deepmimic(edited_walk(tmp_path, nan))

    def inf_knee(frames):
        frames[4][20] = float("inf")  # right knee angle (a 1-DoF hinge)

    with pytest.raises(ValueError, match="right_knee.*frame 4"):
        load_deepmimic(edited_walk(tmp_path, inf_knee))

    def zero(frames):
        frames[3][21:25] = [0.0, 0.0, 0.0, 0.0]  # right ankle quaternion

    with pytest.raises(ValueError, match="frame 3.*zero norm|zero norm.*frame 3"):
        load_deepmimic(edited_walk(tmp_path, zero))

    def short(frames):
        frames[5] = frames[5][:40]

    with pytest.raises(ValueError, match="frame 5 has 40 numbers, expected 44"):
        load_deepmimic(edited_walk(tmp_path, short))


def test_quaternions_are_normalised_on_load(tmp_path, clips):
    def scale(frames):
        for f in frames:
            f[4:8] = [2 * v for v in f[4:8]]

    c = load_deepmimic(edited_walk(tmp_path, scale))
    assert np.abs(c.positions - clips["walk"].positions).max() < 1e-5
    assert np.allclose(np.linalg.norm(c.local_rot, axis=-1), 1.0, atol=1e-6)


def test_clip_validates_shapes_and_values():
    sk = humanoid_skeleton()
    q = np.zeros((4, 15, 4))
    q[..., 0] = 1
    with pytest.raises(ValueError, match=r"local_rot \(F, 15, 4\)"):
        Clip("x", 30, sk, np.zeros((4, 3)), q[:, :3])
    q[2, 4] = np.inf
    with pytest.raises(ValueError, match="right_knee.*frame 2"):
        Clip("x", 30, sk, np.zeros((4, 3)), q)
    q[2, 4] = [1, 0, 0, 0]
    clip = Clip("x", 30, sk, np.zeros((4, 3)), q)
    assert np.allclose(clip.positions[0], sk.rest_positions(), atol=1e-6)
    assert torch.is_tensor(clip.fk()[0])


def test_deepmimic_frame_by_hand(tmp_path):
    """One hand-written DeepMimic frame: joint order, hinge axes and the y-up -> z-up turn."""
    s = math.sqrt(0.5)
    frame = [1 / 30, 1.0, 0.9, 0.5, s, 0.0, s, 0.0]  # root at y-up (1, 0.9, 0.5), yaw +90 deg
    ident = [1.0, 0.0, 0.0, 0.0]
    frame += ident + ident  # chest, neck
    frame += ident + [-math.pi / 2] + ident  # right hip, right knee bent 90 deg, right ankle
    frame += [s, -s, 0.0, 0.0] + [0.0]  # right shoulder -90 deg about x (y-up: forward), elbow
    frame += ident + [0.0] + ident  # left hip, knee, ankle
    frame += ident + [math.pi / 2]  # left shoulder, left elbow bent 90 deg
    assert len(frame) == 44
    path = tmp_path / "pose.txt"
    path.write_text(json.dumps({"Loop": "none", "Frames": [frame, frame]}))
    clip = load_deepmimic(path)
    sk = clip.skeleton
    rest = sk.rest_positions()  # (J, 3) z-up, root at the origin, facing +x

    def bone(name):
        return float(np.linalg.norm(sk.offsets[sk.index(name)]))

    # Expected positions in the root's own frame (x forward, y left, z up), by hand:
    local = {n: rest[sk.index(n)].copy() for n in sk.names}
    # The knee hinge (URDF axis z = the character's right) bends by -90 deg: shin points back.
    local["right_ankle"] = local["right_knee"] + [-bone("right_ankle"), 0, 0]
    # -90 deg about the forward axis raises the right arm sideways, to the character's right.
    sh = local["right_shoulder"]
    local["right_elbow"] = sh + [0, -bone("right_elbow"), 0]
    local["right_wrist"] = sh + [0, -bone("right_elbow") - bone("right_wrist"), 0]
    # The left elbow bends by +90 deg: the forearm points forward.
    local["left_wrist"] = local["left_elbow"] + [bone("left_wrist"), 0, 0]
    # The root turned +90 deg about z (x -> y) and moved to world (1, -0.5, 0.9).
    expect = {n: np.array([-v[1], v[0], v[2]]) + [1.0, -0.5, 0.9] for n, v in local.items()}
    for n in sk.names:
        got = clip.positions[0, sk.index(n)]
        assert np.allclose(got, expect[n], atol=1e-5), (n, got, expect[n])
    assert np.allclose(clip.positions[1], clip.positions[0])
