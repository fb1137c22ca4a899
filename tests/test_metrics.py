"""Metrics of A-MDM §7.3 on hand-made motions whose answers are known."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from minimdm.motion import metrics

# A 3-joint chain: root (0) -> knee (1) -> ankle (2); the ankle is the foot joint.
PARENTS = [-1, 0, 1]
OFFSETS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.4], [0.0, 0.0, -0.5]])
FOOT = [2]


def standing(F: int = 10, xy=(0.0, 0.0)) -> np.ndarray:
    """A static pose with the ankle on the floor (z = 0): (F, 3, 3)."""
    pose = np.array([[0.0, 0.0, 0.9], [0.0, 0.0, 0.5], [0.0, 0.0, 0.0]])
    pose[:, :2] += np.asarray(xy)
    return np.repeat(pose[None], F, axis=0)


def test_static_pose_has_no_sliding_no_acceleration_no_bone_error():
    x = standing()
    L = metrics.skeleton_bone_lengths(OFFSETS, PARENTS)
    assert metrics.foot_sliding(x, FOOT) == 0.0
    assert metrics.joint_acceleration(x) == 0.0
    assert metrics.bone_length_error(x, PARENTS, L) == pytest.approx(0.0, abs=1e-9)
    assert metrics.foot_penetration(x, FOOT) == (0.0, 0.0)


def test_constant_velocity_sliding_foot_on_the_ground():
    # The whole body glides 2 cm per frame along x with the foot on the floor: every frame
    # slides 2 cm with full weight (h = 0), and there is no acceleration.
    F, v = 12, 0.02
    x = standing(F)
    x[..., 0] += v * np.arange(F)[:, None]
    assert metrics.foot_sliding(x, FOOT) == pytest.approx(2.0)
    assert metrics.joint_acceleration(x) == pytest.approx(0.0, abs=1e-9)
    # Lifted above the threshold the same glide is not sliding; halfway it is weighted 2 - 2^0.5.
    lifted = x.copy()
    lifted[..., 2] += 0.03
    assert metrics.foot_sliding(lifted, FOOT) == pytest.approx(0.0)
    half = x.copy()
    half[..., 2] += 0.0125
    assert metrics.foot_sliding(half, FOOT) == pytest.approx(2.0 * (2 - math.sqrt(2)))
    # A foot offset moves the contact level: an ankle resting 8 cm up is "on the ground".
    up = x.copy()
    up[..., 2] += 0.08
    assert metrics.foot_sliding(up, FOOT, foot_offset=0.08) == pytest.approx(2.0)


def test_vertical_motion_is_not_sliding_but_is_acceleration():
    x = standing(5)
    x[2, :, 2] += 0.01  # a 1 cm bump at frame 2 for every joint
    assert metrics.foot_sliding(x, FOOT) == 0.0
    # second differences: frames 1..3 see +1, -2, +1 cm -> mean |a| = 4/3 cm/frame^2
    assert metrics.joint_acceleration(x) == pytest.approx(4 / 3)
    assert metrics.joint_acceleration(x, fps=30) == pytest.approx(4 / 3 * 900)


def test_stretched_bone_gives_known_error():
    x = standing(4)
    x[:, 0, 2] += 0.06  # root 6 cm higher: bone root-knee is 46 cm instead of 40
    L = metrics.skeleton_bone_lengths(OFFSETS, PARENTS)
    assert torch.allclose(L, torch.tensor([0.4, 0.5], dtype=torch.float64))
    # two bones, one off by 6 cm -> mean 3 cm
    assert metrics.bone_length_error(x, PARENTS, L) == pytest.approx(3.0)
    lengths = metrics.bone_lengths(x, PARENTS)
    assert lengths.shape == (4, 2)
    assert torch.allclose(lengths[:, 0], torch.full((4,), 0.46, dtype=torch.float64))


def test_apd_of_two_samples_offset_by_known_distance():
    a = standing(6)
    b = standing(6, xy=(0.3, 0.4))  # every joint 50 cm away
    assert metrics.apd(np.stack([a, b])) == pytest.approx(50.0)
    # three samples on a line at 0, 10, 30 cm: pairwise 10, 30, 20 -> mean 20
    c = [standing(6, xy=(d, 0.0)) for d in (0.0, 0.1, 0.3)]
    assert metrics.apd(np.stack(c)) == pytest.approx(20.0)
    with pytest.raises(ValueError, match="K >= 2"):
        metrics.apd(a[None])


def test_ade_fde_take_the_closest_sample():
    ref = standing(5)
    near = ref.copy()
    near[-1] += [0.0, 0.1, 0.0]  # 10 cm off in the last frame only
    far = ref + np.array([0.2, 0.0, 0.0])  # 20 cm off everywhere
    ade, fde = metrics.ade_fde(np.stack([far, near]), ref)
    assert ade == pytest.approx(10.0 / 5)
    assert fde == pytest.approx(10.0)
    with pytest.raises(ValueError, match="reference must have shape"):
        metrics.ade_fde(np.stack([far, near]), ref[:3])


def test_foot_under_the_ground_in_one_of_four_frames():
    x = standing(4)
    x[1, 2, 2] = -0.02
    freq, dist = metrics.foot_penetration(x, FOOT)
    assert freq == pytest.approx(25.0)
    assert dist == pytest.approx(2.0)
    # within the tolerance it does not count
    assert metrics.foot_penetration(x, FOOT, tolerance=0.03) == (0.0, 0.0)


def test_foot_contact_offsets_and_motion_metrics_row():
    x = standing(8)
    x[..., 2] += 0.07
    assert metrics.foot_contact_offsets(x, FOOT, quantile=0.0) == pytest.approx([0.07])
    samples = np.stack([x, x + np.array([0.1, 0.0, 0.0])])
    row = metrics.motion_metrics(
        samples,
        PARENTS,
        FOOT,
        metrics.skeleton_bone_lengths(OFFSETS, PARENTS),
        reference=x,
        ade_frames=5,
        foot_offset=0.07,
    )
    assert set(row) == {"APD", "ADE", "FDE", "FS", "Bone.Err", "Jnt.Accel", "Pen.Freq", "Pen.Dist"}
    assert row["APD"] == pytest.approx(10.0)
    assert row["ADE"] == pytest.approx(0.0)
    assert row["FS"] == 0.0 and row["Pen.Freq"] == 0.0


def test_mean_std_over_seeds():
    assert metrics.mean_std([1.0, 3.0]) == (2.0, 1.0)
    out = metrics.over_seeds(lambda s: {"a": float(s), "b": 2.0}, [1, 2, 3])
    assert out["a"] == pytest.approx((2.0, math.sqrt(2 / 3)))
    assert out["b"] == (2.0, 0.0)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match=r"positions must have shape"):
        metrics.joint_acceleration(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="finite"):
        metrics.foot_sliding(np.full((3, 3, 3), np.nan), FOOT)
    with pytest.raises(ValueError, match="foot_joints must lie"):
        metrics.foot_sliding(standing(3), [5])
    with pytest.raises(ValueError, match="parents must have 3 entries"):
        metrics.bone_lengths(standing(3), [-1, 0])


@settings(max_examples=25, deadline=None)
@given(
    shift=st.tuples(*[st.floats(-5, 5)] * 3),
    angle=st.floats(-math.pi, math.pi),
    seed=st.integers(0, 2**16),
)
def test_metrics_are_invariant_to_rigid_horizontal_moves(shift, angle, seed):
    """APD and bone error do not change when every sample is rotated about z and shifted."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(3, 5, 3, 3))
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    y = x @ R.T + np.asarray(shift)
    L = np.ones(2)
    assert metrics.apd(y) == pytest.approx(metrics.apd(x), rel=1e-9, abs=1e-9)
    assert metrics.bone_length_error(y, PARENTS, L) == pytest.approx(
        metrics.bone_length_error(x, PARENTS, L), rel=1e-9, abs=1e-9
    )
    assert metrics.joint_acceleration(y) == pytest.approx(
        metrics.joint_acceleration(x), rel=1e-9, abs=1e-9
    )
