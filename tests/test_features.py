"""A-MDM features: layout, round trip on every clip, invariances, normalizer, windows."""

import math

import numpy as np
import pytest
import torch

from minimdm.motion.data import Clip, load_clips
from minimdm.motion.features import (
    FeatureLayout,
    Normalizer,
    StartPose,
    WindowDataset,
    decode,
    decode_clip,
    decode_root,
    encode,
    start_pose_of,
)
from minimdm.motion.skeleton import Skeleton, quat_mul, yaw_matrix


@pytest.fixture(scope="module")
def clips():
    return load_clips(loop_frames=301)  # 300 feature rows for every looping clip


def test_layout_dim_matches_the_guide(clips):
    layout = FeatureLayout.for_skeleton(clips.skeleton)
    assert layout.dim == 183 == 3 + 12 * 15
    parts = [layout.root_vel, layout.yaw_rate, layout.joint_pos, layout.joint_vel, layout.joint_rot]
    assert [p.start for p in parts[1:]] == [p.stop for p in parts[:-1]] and parts[-1].stop == 183
    assert [p.stop - p.start for p in parts] == [2, 1, 45, 45, 90]
    names = layout.names()
    assert len(names) == 183 and names[layout.joint_pos][5] == "pos/chest/z"
    assert FeatureLayout.from_dict(layout.to_dict()) == layout
    with pytest.raises(ValueError, match="dim 180"):
        FeatureLayout.from_dict({**layout.to_dict(), "dim": 180})
    assert (
        encode(clips["walk"]).shape == (300, 183) and encode(clips["walk"]).dtype == torch.float32
    )


def test_round_trip_on_every_clip_within_1mm(clips):
    worst = 0.0
    for c in clips:
        x = encode(c)
        pos = decode(x, start_pose_of(c, 0))
        err = (pos - torch.from_numpy(c.positions[1:])).abs().max().item()
        worst = max(worst, err)
        assert err < 1e-3, c.name
        assert c.n_frames == 301 or not c.loop
    print(f"worst round-trip error {worst:.2e} m")


def test_round_trip_from_the_middle_and_batched(clips):
    a, b = clips["walker/turn_left1"], clips["spin"]
    xa, xb = encode(a), encode(b)
    k = 100
    pos = decode(xa[k:], start_pose_of(a, k))
    assert (pos - torch.from_numpy(a.positions[k + 1 :])).abs().max() < 1e-3
    sa, sb = start_pose_of(a, 0), start_pose_of(b, 0)
    start = StartPose(torch.stack([sa.xy, sb.xy]), torch.stack([sa.heading, sb.heading]))
    both = decode(torch.stack([xa, xb]), start)  # (2, 300, 15, 3)
    assert torch.allclose(both[1], decode(xb, sb), atol=1e-5)
    assert torch.allclose(both[0], decode(xa, {"xy": sa.xy, "heading": sa.heading}), atol=1e-5)


def moved(clip: Clip, yaw: float, shift) -> Clip:
    """The clip turned by ``yaw`` about z and shifted on the ground."""
    R = yaw_matrix(torch.tensor(yaw, dtype=torch.float64)).numpy()
    q = torch.from_numpy(clip.local_rot).double()
    qz = torch.tensor([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)], dtype=torch.float64)
    q[:, 0] = quat_mul(qz.expand(len(q), 4), q[:, 0])
    return Clip(clip.name, clip.fps, clip.skeleton, clip.root_pos @ R.T + shift, q.numpy())


@pytest.mark.parametrize("name", ["walk", "cartwheel", "crawl"])
def test_features_ignore_where_the_character_stands_and_faces(clips, name):
    c = clips[name]
    x = encode(c)
    y = encode(moved(c, 2.0, np.array([3.0, -1.0, 0.0])))
    assert (x - y).abs().max() < 1e-4


def test_root_velocity_and_yaw_rate_on_a_hand_made_motion():
    sk = Skeleton(["root", "head"], [-1, 0], [[0, 0, 0], [0, 0, 0.5]])
    F = 5
    h = 0.3 * torch.arange(F, dtype=torch.float64) + math.pi / 2  # turning left 0.3 rad/frame
    q = torch.zeros(F, 2, 4, dtype=torch.float64)
    q[..., 0] = 1
    q[:, 0, 0], q[:, 0, 3] = torch.cos(h / 2), torch.sin(h / 2)
    root = torch.zeros(F, 3, dtype=torch.float64)
    root[:, 0] = 0.1 * torch.arange(F)  # moving along world +x while facing about +y
    root[:, 2] = 1.0
    x = encode(Clip("turn", 30, sk, root.numpy(), q.numpy()))
    layout = FeatureLayout.for_skeleton(sk)
    assert torch.allclose(x[:, layout.yaw_rate], torch.full((F - 1, 1), 0.3), atol=1e-6)
    # World +x seen from heading h: (cos h, -sin h) * 0.1.
    expect = torch.stack([torch.cos(h[1:]), -torch.sin(h[1:])], -1) * 0.1
    assert torch.allclose(x[:, layout.root_vel], expect.float(), atol=1e-6)
    assert torch.allclose(
        x[:, layout.joint_pos], torch.tensor([0, 0, 1.0, 0, 0, 1.5]).expand(F - 1, 6)
    )
    xy, heading = decode_root(x, StartPose(root[0, :2], h[0]))
    assert torch.allclose(xy, root[1:, :2].float(), atol=1e-6)
    assert torch.allclose(heading, h[1:].float(), atol=1e-6)


def test_decode_rejects_bad_features(clips):
    x = encode(clips["walk"])
    x[17, 40] = float("nan")
    with pytest.raises(ValueError, match="17"):
        decode(x, start_pose_of(clips["walk"], 0))
    with pytest.raises(ValueError, match="3 \\+ 12 J"):
        decode(x[:, :100], start_pose_of(clips["walk"], 0))


def test_decode_clip_rebuilds_rotations(clips):
    c = clips["roll"]
    d = decode_clip(encode(c), start_pose_of(c, 0), c.skeleton)
    assert np.abs(d.positions - c.positions[1:]).max() < 1e-3


def test_normalizer_floor_and_round_trip(clips):
    feats = [encode(c) for c in clips]
    norm = Normalizer.fit(feats, floor=1e-3)
    layout = FeatureLayout.for_skeleton(clips.skeleton)
    root_xy = [layout.joint_pos.start, layout.joint_pos.start + 1]  # the root's own x, y: always 0
    assert torch.all(norm.std[root_xy] == 1e-3)
    assert (norm.std >= 1e-3).all()
    x = torch.cat(feats)
    z = norm.normalize(x)
    assert torch.isfinite(z).all() and z[:, root_xy].abs().max() < 1e-2
    assert z.mean(0)[10:20].abs().max() < 1e-4  # standardised
    assert torch.allclose(norm.denormalize(z), x, atol=1e-5)
    again = Normalizer.from_dict(norm.to_dict())
    assert torch.equal(again.mean, norm.mean) and torch.equal(again.std, norm.std)
    with pytest.raises(ValueError, match="last dim 183"):
        norm.normalize(x[:, :10])
    with pytest.raises(ValueError, match="NaN"):
        Normalizer.fit(torch.full((3, 4), float("nan")))


def test_windows_never_cross_clips():
    lengths = [10, 3, 7]
    arrays = []
    for c, L in enumerate(lengths):
        a = torch.zeros(L, 4)
        a[:, 0], a[:, 1] = c, torch.arange(L)  # column 0: clip id, column 1: frame
        arrays.append(a)
    n = 3
    ds = WindowDataset(arrays, n)
    assert len(ds) == sum(max(0, L - n) for L in lengths) == 7 + 0 + 4
    for i in range(len(ds)):
        w = ds[i]
        assert w.shape == (n + 1, 4)
        assert (w[:, 0] == w[0, 0]).all(), "window crosses a clip boundary"
        assert torch.equal(w[:, 1], w[0, 1] + torch.arange(n + 1))
    assert len(WindowDataset(arrays, n, stride=2)) == 4 + 2
    with pytest.raises(ValueError, match="11 frames"):
        WindowDataset(arrays, 10)
