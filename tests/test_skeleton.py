"""Rotation utilities (property tests) and forward kinematics against hand-computed poses."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from minimdm.motion.skeleton import (
    Skeleton,
    axis_angle_to_matrix,
    axis_angle_to_quat,
    bone_pairs,
    euler_to_matrix,
    forward_kinematics,
    heading_angle,
    humanoid_skeleton,
    matrix_to_6d,
    matrix_to_euler,
    matrix_to_quat,
    quat_inverse,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_slerp,
    quat_to_matrix,
    rotate_about_z,
    sixd_to_matrix,
    to_heading_frame,
    wrap_angle,
    yaw_matrix,
)

F64 = torch.float64
finite = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.lists(finite, min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1)
angles = st.lists(st.floats(-math.pi, math.pi), min_size=3, max_size=3)
orders = st.sampled_from(["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"])


def unit(v) -> torch.Tensor:
    return quat_normalize(torch.tensor(v, dtype=F64))


def rot_z(deg: float) -> torch.Tensor:
    return axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(deg)], dtype=F64))


@settings(max_examples=200, deadline=None)
@given(quats)
def test_quat_matrix_quat_up_to_sign(v):
    q = unit(v)
    R = quat_to_matrix(q)
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=F64), atol=1e-12)
    assert torch.linalg.det(R).item() == pytest.approx(1.0, abs=1e-12)
    q2 = matrix_to_quat(R)
    assert min((q - q2).abs().max(), (q + q2).abs().max()) < 1e-9


@settings(max_examples=200, deadline=None)
@given(quats)
def test_matrix_6d_matrix(v):
    R = quat_to_matrix(unit(v))
    assert torch.allclose(sixd_to_matrix(matrix_to_6d(R)), R, atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(quats, st.floats(0.1, 10.0), st.floats(-0.3, 0.3))
def test_6d_gram_schmidt_gives_a_rotation_from_perturbed_input(v, s, eps):
    d6 = matrix_to_6d(quat_to_matrix(unit(v))) * s + eps
    R = sixd_to_matrix(d6)
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=F64), atol=1e-9)
    assert torch.linalg.det(R).item() == pytest.approx(1.0, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(quats, quats, st.lists(finite, min_size=3, max_size=3))
def test_quat_mul_composes_like_matrices(a, b, v):
    qa, qb, x = unit(a), unit(b), torch.tensor(v, dtype=F64)
    assert torch.allclose(
        quat_to_matrix(quat_mul(qa, qb)), quat_to_matrix(qa) @ quat_to_matrix(qb), atol=1e-12
    )
    assert torch.allclose(quat_rotate(qa, x), quat_to_matrix(qa) @ x, atol=1e-12)
    raw = torch.tensor(a, dtype=F64)  # not unit: the inverse still undoes it
    assert torch.allclose(
        quat_mul(raw, quat_inverse(raw)), torch.tensor([1.0, 0, 0, 0], dtype=F64), atol=1e-12
    )


@settings(max_examples=200, deadline=None)
@given(quats, quats)
def test_slerp_endpoints_and_midpoint(a, b):
    q0, q1 = unit(a), unit(b)
    R0, R1 = quat_to_matrix(q0), quat_to_matrix(q1)
    assert torch.allclose(quat_to_matrix(quat_slerp(q0, q1, 0.0)), R0, atol=1e-9)
    assert torch.allclose(quat_to_matrix(quat_slerp(q0, q1, 1.0)), R1, atol=1e-9)
    # The midpoint is equally far (in angle) from both ends.
    mid = quat_slerp(q0, q1, 0.5)
    d0, d1 = (mid * q0).sum().abs(), (mid * q1).sum().abs()
    assert d0.item() == pytest.approx(d1.item(), abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(angles, orders)
def test_euler_round_trip_any_order(a, order):
    R = euler_to_matrix(torch.tensor(a, dtype=F64), order)
    assert torch.allclose(euler_to_matrix(matrix_to_euler(R, order), order), R, atol=1e-9)


@pytest.mark.parametrize("order", ["ZYX", "XYZ", "ZXY"])
def test_euler_gimbal_lock(order):
    a = torch.tensor([0.3, math.pi / 2, -0.7], dtype=F64)
    R = euler_to_matrix(a, order)
    assert torch.allclose(euler_to_matrix(matrix_to_euler(R, order), order), R, atol=1e-7)


def test_euler_matches_elementary_rotations():
    a = torch.tensor([0.4, -0.2, 1.1], dtype=F64)
    Rz = axis_angle_to_matrix(torch.tensor([0, 0, 0.4], dtype=F64))
    Ry = axis_angle_to_matrix(torch.tensor([0, -0.2, 0], dtype=F64))
    Rx = axis_angle_to_matrix(torch.tensor([1.1, 0, 0], dtype=F64))
    assert torch.allclose(euler_to_matrix(a, "ZYX"), Rz @ Ry @ Rx, atol=1e-12)


def test_axis_angle_small_and_batched():
    aa = torch.tensor([[1e-9, 0, 0], [0, math.pi / 2, 0]], dtype=F64)
    q = axis_angle_to_quat(aa)
    assert torch.allclose(q.norm(dim=-1), torch.ones(2, dtype=F64))
    R = axis_angle_to_matrix(aa[None].expand(3, 2, 3))  # any leading dims
    assert R.shape == (3, 2, 3, 3)
    assert torch.allclose(
        R[0, 1] @ torch.tensor([1.0, 0, 0], dtype=F64),
        torch.tensor([0, 0, -1.0], dtype=F64),
        atol=1e-12,
    )


@settings(max_examples=100, deadline=None)
@given(st.floats(-3.1, 3.1), quats)
def test_heading_is_the_yaw_and_ignores_pitch(yaw, v):
    pitch = axis_angle_to_matrix(torch.tensor([0.0, 0.7, 0.0], dtype=F64))  # about the lateral axis
    R = yaw_matrix(torch.tensor(yaw, dtype=F64)) @ pitch
    assert heading_angle(R).item() == pytest.approx(yaw, abs=1e-9)
    assert wrap_angle(torch.tensor(yaw + 4 * math.pi)).item() == pytest.approx(yaw, abs=1e-6)


headings = st.lists(st.floats(-50.0, 50.0), min_size=1, max_size=5)
coords = st.floats(-10.0, 10.0)


@settings(max_examples=200, deadline=None)
@given(headings, st.integers(1, 4), st.sampled_from([2, 3]), st.integers(0, 2**31 - 1))
def test_rotating_about_z_by_h_then_minus_h_is_the_identity(h, n, dim, seed):
    """Also: the heading frame inverts the rotation, and 3D vectors rotate as ``yaw_matrix``."""
    h = torch.tensor(h, dtype=F64)  # (N,)
    v = torch.randn(len(h), n, dim, generator=torch.Generator().manual_seed(seed), dtype=F64)
    w = rotate_about_z(v, h)  # (N, n, dim): the heading broadcasts over the points
    assert w.shape == v.shape
    assert torch.allclose(rotate_about_z(w, -h), v, atol=1e-12)
    assert torch.allclose(to_heading_frame(w, h), v, atol=1e-12)
    assert torch.allclose(w.norm(dim=-1), v.norm(dim=-1), atol=1e-12)
    if dim == 3:
        R = yaw_matrix(h)[:, None]  # (N, 1, 3, 3)
        assert torch.allclose(w, (R @ v[..., None])[..., 0], atol=1e-12)
        assert torch.equal(w[..., 2], v[..., 2])


@settings(max_examples=200, deadline=None)
@given(st.floats(-50.0, 50.0), st.floats(0.01, 10.0))
def test_a_characters_own_forward_is_plus_x_in_its_heading_frame(h, speed):
    ahead = speed * torch.tensor([math.cos(h), math.sin(h)], dtype=F64)
    left = speed * torch.tensor([-math.sin(h), math.cos(h)], dtype=F64)
    heading = torch.tensor(h, dtype=F64)
    assert torch.allclose(to_heading_frame(ahead, heading), ahead.new_tensor([speed, 0]), atol=1e-9)
    assert torch.allclose(to_heading_frame(left, heading), ahead.new_tensor([0, speed]), atol=1e-9)
    # the frame's axes, back in the world, are the heading's
    assert torch.allclose(rotate_about_z(ahead.new_tensor([speed, 0]), heading), ahead, atol=1e-9)


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e3, 1e3), st.booleans())
def test_wrap_angle_lands_near_zero_and_moves_by_whole_turns(a, include_pi):
    w = wrap_angle(torch.tensor(a, dtype=F64), include_pi).item()
    assert -math.pi <= w <= math.pi  # the open end may round onto pi
    turns = (a - w) / (2 * math.pi)
    assert turns == pytest.approx(round(turns), abs=1e-9)


def test_wrap_angle_keeps_the_end_it_names():
    ends = torch.tensor([math.pi, -math.pi], dtype=F64)
    assert wrap_angle(ends).tolist() == [math.pi, math.pi]  # (-pi, pi]
    assert wrap_angle(ends, include_pi=False).tolist() == [-math.pi, -math.pi]  # [-pi, pi)


def test_bone_pairs_are_the_joints_with_a_parent_in_joint_order():
    assert bone_pairs([-1, 0, 1, 1, 0]) == ([1, 2, 3, 4], [0, 1, 1, 0])
    sk = humanoid_skeleton()
    children, parents = bone_pairs(sk.parents)
    assert len(children) == len(sk.names) - 1
    assert [sk.parents[c] for c in children] == parents


def chain() -> Skeleton:
    """Three joints along +x, 1 m and 0.5 m bones."""
    return Skeleton(
        ["a", "b", "c"], [-1, 0, 1], [[0, 0, 0], [1, 0, 0], [0.5, 0, 0]], foot_joints=["c"]
    )


def test_fk_chain_with_a_90_degree_rotation():
    sk = chain()
    local = torch.stack([torch.eye(3, dtype=F64), rot_z(90), torch.eye(3, dtype=F64)])
    pos, rot = forward_kinematics(sk, torch.tensor([0.0, 0.0, 1.0], dtype=F64), local)
    # b rotates 90 degrees about z, so the bone b -> c points along +y.
    expect = torch.tensor([[0, 0, 1.0], [1, 0, 1.0], [1, 0.5, 1.0]], dtype=F64)
    assert torch.allclose(pos, expect, atol=1e-12)
    assert torch.allclose(rot[2], rot_z(90), atol=1e-12)
    # A root rotation turns the whole chain: root yaw 90 + b yaw 90 -> c at (0, 1) + (-0.5, 0).
    local[0] = rot_z(90)
    pos, _ = forward_kinematics(sk, torch.zeros(3, dtype=F64), local)
    assert torch.allclose(pos[2], torch.tensor([-0.5, 1.0, 0.0], dtype=F64), atol=1e-12)


def test_fk_quaternions_and_batch_dims():
    sk = chain()
    q = quat_normalize(
        torch.randn(4, 5, 3, 4, dtype=F64, generator=torch.Generator().manual_seed(0))
    )
    root = torch.randn(4, 5, 3, dtype=F64, generator=torch.Generator().manual_seed(1))
    p_q, R_q = forward_kinematics(sk, root, q)
    p_m, R_m = forward_kinematics(sk, root, quat_to_matrix(q))
    assert p_q.shape == (4, 5, 3, 3) and R_q.shape == (4, 5, 3, 3, 3)
    assert torch.allclose(p_q, p_m) and torch.allclose(R_q, R_m)
    # Bone lengths are preserved by any rotation.
    assert torch.allclose(
        (p_q[..., 2, :] - p_q[..., 1, :]).norm(dim=-1), torch.full((4, 5), 0.5, dtype=F64)
    )
    with pytest.raises(ValueError, match="local_rot"):
        forward_kinematics(sk, root, q[..., :2, :])


def test_humanoid_rest_pose():
    sk = humanoid_skeleton()
    assert sk.names == [
        "root", "chest", "neck", "right_hip", "right_knee", "right_ankle", "right_shoulder",
        "right_elbow", "right_wrist", "left_hip", "left_knee", "left_ankle", "left_shoulder",
        "left_elbow", "left_wrist",
    ]  # fmt: skip
    assert all(p < j for j, p in enumerate(sk.parents))
    assert sk.parents[sk.index("right_wrist")] == sk.index("right_elbow")
    rest = sk.rest_positions()
    # URDF origins x 0.25: chest 0.944604*0.25 above the root, ankle 0.25*(1.686184+1.63948) below.
    assert rest[sk.index("chest"), 2] == pytest.approx(0.944604 * 0.25)
    assert rest[sk.index("left_ankle"), 2] == pytest.approx(-0.25 * (1.686184 + 1.63948))
    assert rest[sk.index("neck"), 2] > rest[sk.index("chest"), 2] > 0
    # Left is +y, the shoulders sit slightly behind the spine (-x).
    assert rest[sk.index("left_hip"), 1] == pytest.approx(0.339548 * 0.25)
    assert rest[sk.index("right_hip"), 1] == pytest.approx(-0.339548 * 0.25)
    assert rest[sk.index("left_shoulder"), 0] == pytest.approx(-0.0962 * 0.25)
    assert sk.bone_lengths()[sk.index("right_knee")] == pytest.approx(1.686184 * 0.25)
    assert sk.foot_indices == [sk.index("right_ankle"), sk.index("left_ankle")]


def test_skeleton_dict_round_trip_and_validation():
    sk = humanoid_skeleton()
    assert Skeleton.from_dict(sk.to_dict()) == sk
    assert sk != chain()
    other = Skeleton.from_dict({**sk.to_dict(), "offsets": (sk.offsets * 1.1).tolist()})
    assert other != sk
    with pytest.raises(ValueError, match="parent"):
        Skeleton(["a", "b"], [-1, 1], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="unique"):
        Skeleton(["a", "a"], [-1, 0], np.zeros((2, 3)))
    with pytest.raises(KeyError, match="no joint"):
        sk.index("head")
