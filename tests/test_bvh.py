"""BVH: a hand-written file with known positions, the save/load round trip, malformed files."""

import numpy as np
import pytest

from minimdm.motion.bvh import BVHError, load_bvh, save_bvh
from minimdm.motion.data import load_clips

TINY = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT LeftUpLeg
  {
    OFFSET 10 0 0
    CHANNELS 3 Xrotation Yrotation Zrotation
    JOINT LeftFoot
    {
      OFFSET 0 -40 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 0 15
      }
    }
  }
  JOINT RightUpLeg
  {
    OFFSET -10 0 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 -40 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
0 90 0 0 0 0 0 0 0 0 0 0 0 0 0
100 90 0 90 0 0 90 90 0 0 0 0 0 0 0
"""
TINY_MOTION_LINE = TINY.splitlines().index("MOTION") + 1


def line_of(text: str) -> int:
    """1-based line of TINY that starts with ``text`` (after indentation)."""
    return next(i for i, ln in enumerate(TINY.splitlines(), 1) if ln.strip().startswith(text))


def write(tmp_path, text, name="tiny.bvh"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_tiny_bvh_known_positions(tmp_path):
    clip = load_bvh(write(tmp_path, TINY), scale=0.01)
    sk = clip.skeleton
    assert sk.names == ["Hips", "LeftUpLeg", "LeftFoot", "RightUpLeg"]  # End Sites dropped
    assert sk.parents == [-1, 0, 1, 0]
    # BVH (X left, Y up, Z forward) in cm -> world (x forward, y left, z up) in m.
    assert np.allclose(sk.offsets, [[0, 0, 0], [0, 0.1, 0], [0, 0, -0.4], [0, -0.1, 0]])
    assert sk.foot_joints == ["LeftFoot"] and np.allclose(sk.lateral_axis, [0, 1, 0])
    assert clip.fps == 30 and clip.n_frames == 2
    p = clip.positions
    assert np.allclose(p[0], [[0, 0, 0.9], [0, 0.1, 0.9], [0, 0.1, 0.5], [0, -0.1, 0.9]], atol=1e-6)
    # Frame 1: root moved 1 m along BVH X (world y) and turned 90 degrees about BVH Y (up);
    # the leg's Xrotation 90 then Yrotation 90 (in that order) swings the foot to BVH -Z.
    assert np.allclose(p[1, 0], [0, 1.0, 0.9], atol=1e-6)
    assert np.allclose(p[1, 1], [0, 1.0, 1.0], atol=1e-6)
    assert np.allclose(p[1, 2], [-0.4, 1.0, 1.0], atol=1e-6)
    assert np.allclose(p[1, 3], [0, 1.0, 0.8], atol=1e-6)


def test_bvh_frame_rate_is_resampled_to_30(tmp_path):
    lines = TINY.splitlines()[:TINY_MOTION_LINE]
    rows = [f"{i} 90 0 0 0 0 0 0 0 0 0 0 0 0 0" for i in range(9)]  # 9 frames at 60 Hz
    text = "\n".join(lines + ["Frames: 9", "Frame Time: 0.0166667", *rows]) + "\n"
    clip = load_bvh(write(tmp_path, text), scale=0.01)
    assert clip.fps == 30 and clip.n_frames == 5
    assert np.allclose(clip.root_pos[:, 1], [0.0, 0.02, 0.04, 0.06, 0.08], atol=1e-5)
    assert load_bvh(write(tmp_path, text), fps=None, scale=0.01).n_frames == 9


@pytest.mark.parametrize("scale", [1.0, 100.0])
def test_save_load_round_trip_same_positions(tmp_path, scale):
    clips = load_clips(loop_frames=120, names=["cartwheel", "walker/turn_left0", "backflip"])
    for clip in clips:
        path = tmp_path / f"{clip.name.replace('/', '_')}.bvh"
        save_bvh(path, clip, scale=scale)
        back = load_bvh(path)  # the scale (m or cm) is guessed from the body size
        assert back.n_frames == clip.n_frames and back.fps == pytest.approx(30)
        assert back.skeleton.names[:3] == ["root", "chest", "neck"]  # written depth first
        back = back.reorder(clip.skeleton.names)
        assert back.skeleton == clip.skeleton
        assert np.abs(back.positions - clip.positions).max() < 1e-4, clip.name
    text = path.read_text()
    assert "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation" in text
    assert text.count("End Site") == 5  # neck, wrists, ankles


def test_load_folder(tmp_path):
    (tmp_path / "sub").mkdir()
    write(tmp_path, TINY, "a.bvh")
    write(tmp_path, TINY, "sub/b.bvh")
    ds = load_bvh(tmp_path, scale=0.01)
    assert ds.names == ["a", "sub/b"] and ds.skeleton.names[0] == "Hips"


def test_animated_child_translation_warns(tmp_path):
    head = TINY.split("MOTION")[0].replace(
        "CHANNELS 3 Xrotation Yrotation Zrotation",
        "CHANNELS 4 Xposition Xrotation Yrotation Zrotation",
    )
    rows = ["0 90 0 0 0 0 10 0 0 0 0 0 0 0 0 0", "100 90 0 90 0 0 12 90 90 0 0 0 0 0 0 0"]
    text = head + "MOTION\nFrames: 2\nFrame Time: 0.0333333\n" + "\n".join(rows) + "\n"
    with pytest.warns(UserWarning, match="LeftUpLeg"):
        load_bvh(write(tmp_path, text), scale=0.01)


def broken(old: str, new: str) -> str:
    assert old in TINY
    return TINY.replace(old, new, 1)


@pytest.mark.parametrize(
    "text, line, what",
    [
        (broken("ROOT Hips\n{", "ROOT Hips\n"), line_of("OFFSET 0 0 0"), "expected '{'"),
        (
            broken("OFFSET 10 0 0", "OFFSET 10 0"),
            line_of("OFFSET 10 0 0") + 1,
            "expected an OFFSET number, got 'CHANNELS'",
        ),
        (
            broken("Xrotation Yrotation Zrotation", "Xrotation Wrotation Zrotation"),
            line_of("CHANNELS 3 Xrot"),
            "channel name",
        ),
        (
            broken("  JOINT RightUpLeg", "  JOIN RightUpLeg"),
            line_of("JOINT RightUpLeg"),
            "expected JOINT, End Site or '}'",
        ),
        (broken("Frames: 2", "Frames: two"), TINY_MOTION_LINE + 1, "Frames: <integer>"),
        (
            broken("0 90 0 0 0 0 0 0 0 0 0 0 0 0 0", "0 90 0 0 0"),
            TINY_MOTION_LINE + 3,
            "expected 15 channel values, got 5",
        ),
        (broken("100 90 0 90", "100 90 x 90"), TINY_MOTION_LINE + 4, "expected a number, got 'x'"),
        (broken("100 90 0 90", "100 90 nan 90"), TINY_MOTION_LINE + 4, "frame 1 holds NaN/Inf"),
        (broken("OFFSET 10 0 0", "OFFSET 10 inf 0"), line_of("OFFSET 10 0 0"), "OFFSET number"),
        (broken("Frames: 2", "Frames: 3"), TINY_MOTION_LINE + 4, "expected 3 frames"),
        (TINY.split("MOTION")[0], TINY_MOTION_LINE - 1, "expected MOTION, got end of file"),
        (broken("  }\n}\nMOTION", "  }\nMOTION"), TINY_MOTION_LINE - 1, "got end of hierarchy"),
    ],
)
def test_malformed_bvh_names_the_line(tmp_path, text, line, what):
    path = write(tmp_path, text)
    with pytest.raises(BVHError) as e:
        load_bvh(path)
    assert f"tiny.bvh:{line}:" in str(e.value) and what in str(e.value), str(e.value)
