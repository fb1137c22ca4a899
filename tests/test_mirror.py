"""Left/right mirroring (minimdm.motion.mirror): the positions are the mirror image, the
features flip their lateral parts, and mirroring twice gives the clip back."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from minimdm.motion.corpora import load_corpus
from minimdm.motion.data import Clip
from minimdm.motion.features import encode
from minimdm.motion.mirror import joint_partners, mirror_clip, mirror_clips
from minimdm.motion.skeleton import Skeleton, axis_angle_to_quat

REFLECT = np.array([1.0, -1.0, 1.0])

TAKES = ["dataset-1_walk-left_proud_001", "dataset-1_run_happy_001"]


@pytest.fixture(scope="module")
def takes():
    return load_corpus("bandai-namco-1", split="test", takes=TAKES)


def legged(flipped_leg_frames: bool) -> Skeleton:
    """Hips, a spine and two three-bone legs; ``flipped_leg_frames``: the right leg's bones run
    along -y in its frames while the left's run along +y, as in the Bandai-Namco rig."""
    s = -1.0 if flipped_leg_frames else 1.0
    names = ["Hips", "Spine", "UpperLeg_L", "LowerLeg_L", "Foot_L", "UpperLeg_R", "LowerLeg_R",
             "Foot_R"]  # fmt: skip
    parents = [-1, 0, 0, 2, 3, 0, 5, 6]
    offsets = [[0, 0, 1.0], [0, 0, 0.2], [0, 0.1, -0.05], [0, 0, -0.45], [0, 0, -0.4],
               [0, -0.1, -0.05], [0, 0, -0.45 * s], [0, 0, -0.4 * s]]  # fmt: skip
    return Skeleton(names, parents, offsets, foot_joints=["Foot_L", "Foot_R"])


def test_partners_pair_left_with_right():
    sk = legged(False)
    p = joint_partners(sk)
    assert [sk.names[j] for j in p] == ["Hips", "Spine", "UpperLeg_R", "LowerLeg_R", "Foot_R",
                                        "UpperLeg_L", "LowerLeg_L", "Foot_L"]  # fmt: skip


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), flipped=st.booleans())
def test_a_mirrored_clip_is_the_mirror_image_and_mirrors_back(seed, flipped):
    sk = legged(flipped)
    g = torch.Generator().manual_seed(seed)
    F = 6
    rot = axis_angle_to_quat(0.6 * torch.randn(F, len(sk), 3, generator=g, dtype=torch.float64))
    root = torch.randn(F, 3, generator=g, dtype=torch.float64).numpy()
    clip = Clip("c", 30.0, sk, root, rot.numpy())
    m = mirror_clip(clip)
    partner = joint_partners(sk)
    np.testing.assert_allclose(m.positions, clip.positions[:, partner] * REFLECT, atol=1e-5)
    back = mirror_clip(m)
    same = np.minimum(
        np.abs(back.local_rot - clip.local_rot).max(-1),
        np.abs(back.local_rot + clip.local_rot).max(-1),
    )  # q and -q are one rotation
    assert same.max() < 1e-6


def test_mirrored_takes_flip_the_lateral_features(takes):
    mirrored = mirror_clips(list(takes))
    for clip, m in zip(takes, mirrored, strict=True):
        assert m.name == f"{clip.name}~mirror" and m.labels == clip.labels
        partner = joint_partners(clip.skeleton)
        # the actor is nearly symmetric: within a millimetre of the mirror image
        assert np.abs(m.positions - clip.positions[:, partner] * REFLECT).max() < 1e-3
        a, b = encode(clip), encode(m)
        torch.testing.assert_close(b[:, 0], a[:, 0], atol=1e-5, rtol=0)  # forward speed
        torch.testing.assert_close(b[:, 1], -a[:, 1], atol=1e-5, rtol=0)  # sideways: flipped
        torch.testing.assert_close(b[:, 2], -a[:, 2], atol=1e-5, rtol=0)  # turning: flipped
    # a walk to the left (0.14 m/s sideways) becomes a walk to the right
    i = list(takes.names).index("dataset-1_walk-left_proud_001")
    assert encode(takes[i])[:, 1].mean() * 30 > 0.1
    assert encode(mirrored[i])[:, 1].mean() * 30 < -0.1


def test_a_rig_without_mirror_partners_is_refused():
    sk = Skeleton(["Hips", "Arm_L", "Arm_R"], [-1, 0, 0], [[0, 0, 1], [0, 0.2, 0], [0.3, 0, 0]])
    clip = Clip("c", 30.0, sk, np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 3, 1)))
    with pytest.raises(ValueError, match="cannot mirror the skeleton: .*Hips"):
        mirror_clip(clip)
