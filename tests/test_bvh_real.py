"""BVH import against an independent reader (bvhio), on the bundled corpus and on written files
with unusual channel layouts; the units guess; bounds on bad headers."""

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from minimdm.motion.bvh import BVH_TO_WORLD, BVHError, load_bvh

bvhio = pytest.importorskip("bvhio", reason="pip install bvhio (a test dependency of minimdm)")


def bvhio_positions(path) -> tuple[list[str], np.ndarray]:
    """Joint names and global positions (F, J, 3) in the file's units and axes, read by bvhio."""
    root = bvhio.readAsHierarchy(str(path))
    joints = [j for j, _, _ in root.layout()]
    n = root.getKeyframeRange()[1] + 1
    out = np.empty((n, len(joints), 3))
    for f in range(n):
        root.loadPose(f)
        out[f] = [np.array(j.PositionWorld, dtype=np.float64) for j in joints]
    return [j.Name for j in joints], out


def max_error_m(path, scale: float) -> tuple[float, object]:
    """Largest joint distance in metres between our clip and bvhio, matched by joint name."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        clip = load_bvh(path, fps=None, scale=scale)
    names, ref = bvhio_positions(path)
    ref = ref @ BVH_TO_WORLD.T * scale  # file axes and units -> our z-up world in metres
    ours = clip.fk()[0].numpy()  # (F, J, 3)
    idx = [names.index(n) for n in clip.skeleton.names]
    return float(np.linalg.norm(ours - ref[:, idx], axis=-1).max()), clip


# --------------------------------------------------------------------------- the corpus

TAKES = [
    "dataset-1_walk_normal_001",
    "dataset-1_run_normal_001",  # here joint_Root carries part of the path
    "dataset-1_run_happy_001",
    "dataset-1_walk-left_giant_001",
    "dataset-1_bow_old_001",
    "dataset-1_kick_normal_001",
]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    from minimdm.motion.corpora import corpus_path

    mp = pytest.MonkeyPatch()
    mp.setenv("MINIMDM_DATA", str(tmp_path_factory.mktemp("data")))
    yield corpus_path("bandai-namco-1") / "data"
    mp.undo()


@pytest.mark.parametrize("take", TAKES)
def test_corpus_takes_match_bvhio_within_1mm(corpus, take):
    err, clip = max_error_m(corpus / f"{take}.bvh", 0.01)
    assert err < 1e-3, f"{take}: {err * 1000:.3f} mm from bvhio"
    # joint_Root is folded into the hips: the clip's root is the hips, which carry the path
    assert clip.skeleton.names[0] == "Hips" and "joint_Root" not in clip.skeleton.names
    names, ref = bvhio_positions(corpus / f"{take}.bvh")
    hips = names.index("Hips")
    travel_ref = np.linalg.norm(ref[-1, hips, [0, 2]] - ref[0, hips, [0, 2]]) * 0.01
    travel = np.linalg.norm(clip.root_pos[-1, :2] - clip.root_pos[0, :2])
    assert travel == pytest.approx(travel_ref, abs=1e-4)


def test_walk_travels_and_units_are_guessed(corpus):
    clip = load_bvh(corpus / "dataset-1_walk_normal_001.bvh")  # scale guessed, 30 Hz
    assert np.linalg.norm(clip.root_pos[-1, :2] - clip.root_pos[0, :2]) > 5.0  # metres
    height = np.ptp(clip.fk()[0].numpy()[..., 2], axis=1)  # (F,) vertical joint extent
    assert 1.2 < np.median(height) < 2.0
    assert clip.fps == 30.0


# --------------------------------------------------------------------------- written files

AXES = "XYZ"


def joint_block(name, offset, chans, depth, children, end=None):
    tab = "  " * depth
    kw = "ROOT" if depth == 0 else "JOINT"
    out = [f"{tab}{kw} {name}", f"{tab}{{", f"{tab}  OFFSET {offset[0]} {offset[1]} {offset[2]}"]
    if chans:
        out.append(f"{tab}  CHANNELS {len(chans)} {' '.join(chans)}")
    for c in children:
        out += c
    if end is not None:
        out += [f"{tab}  End Site", f"{tab}  {{", f"{tab}    OFFSET 0 {end} 0", f"{tab}  }}"]
    out.append(f"{tab}}}")
    return out


@st.composite
def bvh_files(draw):
    """A root on the floor, hips carrying the path, a chain of 3 joints; any channel layout.

    The root moves and turns too (in some Bandai-Namco takes it carries part of the path)."""
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    unit = draw(st.sampled_from([1.0, 100.0, 39.37]))  # metres, centimetres, inches
    n_frames = draw(st.integers(1, 6))

    def rot_chans():
        order = draw(st.permutations(AXES))
        return [f"{a}rotation" for a in order]

    def layout(six: bool):
        pos = [f"{a}position" for a in AXES]
        rot = rot_chans()
        if not six:
            return rot
        return pos + rot if draw(st.booleans()) else rot + pos

    names = ["Root", "Hips", "Spine", "Chest", "Head"]
    offsets = [np.zeros(3)] + [rng.normal(size=3) * 0.2 * unit for _ in names[1:]]
    offsets[1] = np.array([0.0, 0.9, 0.0]) * unit
    chans = [layout(True), layout(True)] + [layout(draw(st.booleans())) for _ in names[2:]]
    values = []
    for f in range(n_frames):
        row = []
        for j, cs in enumerate(chans):
            for c in cs:
                if c.endswith("position"):
                    axis = AXES.index(c[0])
                    if j == 0:
                        row.append(float(rng.normal()) * unit)
                    elif j == 1:
                        row.append(offsets[1][axis] + (0.3 * f * unit if axis == 2 else 0.0))
                    else:
                        row.append(offsets[j][axis])  # constant: only the root path moves
                else:
                    row.append(float(rng.uniform(-170, 170)))
        values.append(row)
    block = None
    for j in range(len(names) - 1, -1, -1):
        kids = [block] if block is not None else []
        end = 0.1 * unit if j == len(names) - 1 else None
        block = joint_block(names[j], offsets[j], chans[j], j, kids, end)
    text = "\n".join(
        ["HIERARCHY", *block, "MOTION", f"Frames: {n_frames}", "Frame Time: 0.0333333"]
        + [" ".join(f"{v:.6f}" for v in row) for row in values]
    )
    return text, unit


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(bvh_files())
def test_any_channel_layout_matches_bvhio(tmp_path, case):
    text, unit = case
    path = tmp_path / "case.bvh"
    path.write_text(text)
    err, clip = max_error_m(path, 1.0 / unit)
    assert err < 1e-5  # bvhio computes in float32
    assert clip.skeleton.names[0] == "Hips"  # the root on the floor was folded


def test_units_guess_from_standing_size(tmp_path, corpus):
    """Centimetres give 0.01, metres 1, inches a body of human size (not a power of ten)."""
    src = (corpus / "dataset-1_walk_normal_001.bvh").read_text()
    lines = src.splitlines()
    motion = lines.index("MOTION")

    def scaled(k: float) -> str:
        out = []
        for i, ln in enumerate(lines):
            w = ln.split()
            if w and w[0] == "OFFSET":
                ln = (
                    ln[: ln.index("OFFSET")]
                    + "OFFSET "
                    + " ".join(str(float(x) * k) for x in w[1:])
                )
            elif i > motion + 2:
                v = np.array(w, dtype=float).reshape(-1, 6)
                v[:, :3] *= k  # every joint has 6 channels, positions first
                ln = " ".join(f"{x:.6f}" for x in v.ravel())
            out.append(ln)
        return "\n".join(out)

    heights = {}
    for k, name in [(1.0, "cm"), (0.01, "m"), (1 / 2.54, "inch")]:
        path = tmp_path / f"{name}.bvh"
        path.write_text(scaled(k))
        clip = load_bvh(path, fps=None)
        heights[name] = float(np.median(np.ptp(clip.fk()[0].numpy()[..., 2], axis=1)))
    assert heights["cm"] == pytest.approx(heights["m"], rel=1e-6)
    assert 1.2 < heights["inch"] < 2.0
    # an explicit scale wins
    clip = load_bvh(tmp_path / "cm.bvh", fps=None, scale=0.02)
    assert float(np.median(np.ptp(clip.fk()[0].numpy()[..., 2], axis=1))) == pytest.approx(
        2 * heights["cm"], rel=1e-6
    )


SIMPLE = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Head
  {
    OFFSET %s
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 10 0
    }
  }
}
MOTION
Frames: 5
Frame Time: %s
""" + "\n".join(["0 90 0 0 0 0 0 0 0"] * 5)


@pytest.mark.parametrize(
    "offset, frame_time, words",
    [
        ("0 60 0", "1e6", ["Frame Time", "frames per second"]),
        ("0 60 0", "1e-9", ["Frame Time", "frames per second"]),
        ("0 1e308 0", "0.0333", ["cannot guess the units", "scale="]),
    ],
)
def test_bad_headers_are_refused(tmp_path, offset, frame_time, words):
    path = tmp_path / "bad.bvh"
    path.write_text(SIMPLE % (offset, frame_time))
    with pytest.raises(BVHError) as e:
        load_bvh(path)
    assert all(w in str(e.value) for w in words) and str(path) in str(e.value)


def test_all_zero_offsets_ask_for_scale(tmp_path):
    path = tmp_path / "flat.bvh"
    path.write_text((SIMPLE % ("0 0 0", "0.0333")).replace("0 90 0 0", "0 0 0 0"))
    with pytest.raises(BVHError, match="scale="):
        load_bvh(path)


def test_resampling_is_bounded(tmp_path, monkeypatch):
    from minimdm.motion import bvh

    monkeypatch.setattr(bvh, "MAX_FRAMES", 10)
    path = tmp_path / "slow.bvh"
    path.write_text(SIMPLE % ("0 60 0", "0.5"))  # 5 frames of 0.5 s: 61 frames at 30 Hz
    with pytest.raises(BVHError, match="more than 10 frames"):
        load_bvh(path)
    assert load_bvh(path, fps=None).n_frames == 5


def test_bom_latin1_and_duplicate_names(tmp_path):
    text = SIMPLE % ("0 60 0", "0.0333")
    path = tmp_path / "bom.bvh"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert load_bvh(path, fps=None).skeleton.names == ["Hips", "Head"]
    path.write_bytes(text.replace("Head", "T\xeate").encode("latin-1"))
    assert load_bvh(path, fps=None).skeleton.names == ["Hips", "T\xeate"]
    path.write_text(text.replace("JOINT Head", "JOINT Hips"))
    with pytest.raises(BVHError, match=r"bom.bvh:6: joint name 'Hips' is used twice"):
        load_bvh(path)
