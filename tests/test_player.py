"""The 3D player's payload and HTML (minimdm.viz.payload, minimdm.viz.webplayer).

What the page does with them is tested in a real browser by tests/test_browser.py.
"""

import base64
import gzip
import json
import re

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from minimdm import viz
from minimdm.motion.skeleton import Skeleton, forward_kinematics, quat_normalize
from minimdm.viz import payload as pl
from minimdm.viz import webplayer as pmod

PARENTS = [-1, 0, 1, 0, 3]  # a root with two chains of two


def walk(T=30, J=5, speed=1.0, seed=0, noise=0.02):
    """(T, J, 3) positions: a stick figure moving along +x with wobbling joints."""
    rng = np.random.default_rng(seed)
    base = np.array([[0, 0, 1.0], [0, 0.1, 0.5], [0, 0.1, 0.05], [0, -0.1, 0.5], [0, -0.1, 0.05]])
    t = np.arange(T)[:, None, None] / 30.0
    x = base[None, :J] + noise * rng.standard_normal((T, J, 3))
    x[..., 0] += speed * t[..., 0]
    return x


def skeleton5():
    offsets = np.array([[0, 0, 1.0], [0, 0.1, -0.5], [0, 0, -0.45], [0, -0.1, -0.5], [0, 0, -0.45]])
    names = ["root", "left_knee", "left_foot", "right_knee", "right_foot"]
    return Skeleton(names, PARENTS, offsets, foot_joints=["left_foot", "right_foot"])


# --------------------------------------------------------------------------- the payload


@settings(max_examples=40, deadline=None)
@given(
    arrays(
        np.float64,
        st.tuples(st.integers(1, 40), st.integers(1, 6), st.just(3)),
        elements=st.floats(-60, 60, allow_nan=False, width=32),
    )
)
def test_positions_round_trip_within_half_a_step(x):
    p = pl.build_payload(x, [-1] + list(range(x.shape[1] - 1)), feet=False)
    m = p["motions"][0]
    back = pl.decode_positions(m, x.shape[1])
    assert back.shape == x.shape
    step = np.asarray(m["step"])
    assert (step >= pl.MIN_STEP).all()
    assert (np.abs(back - x) <= step / 2 + 1e-9).all()


def test_walk_is_compact_and_accurate():
    x = walk(T=300, speed=1.4)
    p = pl.build_payload(x, PARENTS, feet=False)
    back = pl.decode_positions(p["motions"][0], 5)
    assert np.abs(back - x).max() <= 0.5e-3 + 1e-12  # 1 mm steps
    raw = 300 * 5 * 3 * 4  # float32
    assert len(p["motions"][0]["data"]) < raw / 2  # quantised, differenced, gzipped


def test_torch_batch_list_and_lengths():
    a, b = walk(T=30), walk(T=12, seed=1)
    p = pl.build_payload([torch.from_numpy(a).float(), b], PARENTS, feet=False)
    assert [m["n"] for m in p["motions"]] == [30, 12]
    np.testing.assert_allclose(pl.decode_positions(p["motions"][1], 5), b, atol=6e-4)
    batch = np.stack([a, walk(T=30, seed=2)])
    assert len(pl.build_payload(batch, PARENTS, feet=False)["motions"]) == 2


def test_rotations_go_through_forward_kinematics():
    sk = skeleton5()
    g = torch.Generator().manual_seed(0)
    rot = quat_normalize(torch.randn(20, 5, 4, generator=g, dtype=torch.float64))
    root = torch.randn(20, 3, generator=g, dtype=torch.float64)
    p = pl.build_payload((root, rot), sk)
    want = forward_kinematics(sk, root, rot)[0].numpy()
    np.testing.assert_allclose(pl.decode_positions(p["motions"][0], 5), want, atol=6e-4)
    assert p["names"] == sk.names and p["feet"] == [2, 4]


def test_side_layout_puts_lanes_apart_and_overlay_does_not():
    ms = [walk(T=40, seed=s) for s in range(3)]  # all on the same spot, walking along x
    p = pl.build_payload(ms, PARENTS, layout="side", feet=False)
    assert p["lane_axis"] == 1  # they travel along x, so the lanes lie across, along y
    spans = []
    for m, x in zip(p["motions"], ms, strict=True):
        y = x[..., 1] + m["offset"][1]
        spans.append((y.min(), y.max()))
        assert m["offset"][0] == m["offset"][2] == 0
    spans.sort()
    for (_, hi), (lo, _) in zip(spans, spans[1:], strict=False):
        assert lo - hi >= pl.LANE_GAP - 1e-3
    over = pl.build_payload(ms, PARENTS, layout="overlay", feet=False)
    assert all(m["offset"] == [0.0, 0.0, 0.0] for m in over["motions"])


def test_contacts_detected_and_given():
    x = walk(T=20, speed=0.0, noise=0.0)
    x[10:, 2, 2] += 0.2  # the left foot lifts at frame 10
    p = pl.build_payload(x, skeleton5())
    c = pl.decode_contacts(p["motions"][0], 2)
    assert c[:10, 0].all() and not c[10:, 0].any() and c[:, 1].all()
    given_ = np.zeros((20, 2), bool)
    given_[::3, 1] = True
    p = pl.build_payload([x], skeleton5(), contacts=[given_])
    np.testing.assert_array_equal(pl.decode_contacts(p["motions"][0], 2), given_)


def test_targets_paths_keyframes_for_all_or_per_motion():
    ms = [walk(T=30), walk(T=30, seed=1)]
    pose = ms[0][5]
    p = pl.build_payload(
        ms,
        PARENTS,
        feet=False,
        targets=[[2.0, 0.5], [3.0, -1.0]],  # two ground points, for both characters
        paths=[np.zeros((4, 2)), None],  # a path for the first only
        keyframes={"frames": [5], "poses": pose[None]},
    )
    kinds = {(s["kind"], s["motion"]) for s in p["shapes"]}
    assert kinds == {("target", -1), ("path", 0), ("keyframes", -1)}
    target = next(s for s in p["shapes"] if s["kind"] == "target")
    assert target["points"] == [[2.0, 0.5, 0.0], [3.0, -1.0, 0.0]]
    key = next(s for s in p["shapes"] if s["kind"] == "keyframes")
    assert key["frames"] == [5]
    np.testing.assert_allclose(np.reshape(key["poses"], (1, 5, 3)), pose[None], atol=1e-4)


BAD = [
    ("nan", lambda: (np.where(np.arange(30)[:, None, None] == 7, np.nan, walk()), PARENTS, {}),
     r"must be finite.*frame 7"),
    ("inf", lambda: ([walk(), np.full((3, 5, 3), np.inf)], PARENTS, {}),
     r"motions\[1\] must be finite"),
    ("zero frames", lambda: (np.zeros((0, 5, 3)), PARENTS, {}), "at least one frame"),
    ("empty list", lambda: ([], PARENTS, {}), "at least one motion"),
    ("xy only", lambda: (np.zeros((4, 5, 2)), PARENTS, {}), r"shape \(T, J, 3\)"),
    ("one frame 2D", lambda: (np.zeros((5, 3)), PARENTS, {}), r"shape \(T, J, 3\)"),
    ("short parents", lambda: (walk(), PARENTS[:4], {}), "J = 5 joints, the parents list has 4"),
    ("parent after child", lambda: (walk(), [-1, 0, 3, 0, 3], {}), r"parents\[2\] .* got 3"),
    ("parent out of range", lambda: (walk(), [-1, 0, 1, 0, 9], {}), r"parents\[4\]"),
    ("mixed joint counts", lambda: ([walk(), walk()[:, :4]], PARENTS, {}), "joint counts"),
    ("labels", lambda: (walk(), PARENTS, {"labels": ["a", "b"]}), "one label per motion"),
    ("colours", lambda: ([walk(), walk()], PARENTS, {"colors": ["red"] * 3}), "one colour"),
    ("layout", lambda: (walk(), PARENTS, {"layout": "grid"}), "layout must be one of"),
    ("fps", lambda: (walk(), PARENTS, {"fps": 0}), "fps must be"),
    ("target NaN", lambda: (walk(), PARENTS, {"targets": [[np.nan, 0.0]]}),
     "targets must be finite"),
    ("keyframe past the horizon", lambda: (walk(), PARENTS,
     {"keyframes": ([30], walk()[:1])}), r"keyframes frames must lie in \[0, 30\)"),
    ("keyframe shape", lambda: (walk(), PARENTS, {"keyframes": np.zeros((2, 4, 3))}),
     r"\(K, 5, 3\)"),
    ("no keyframes", lambda: (walk(), PARENTS, {"keyframes": np.zeros((0, 5, 3))}), "K >= 1"),
    ("contacts shape", lambda: (walk(), skeleton5(), {"contacts": [np.zeros((29, 2))]}),
     r"contacts\[0\] must have shape"),
    ("foot name", lambda: (walk(), skeleton5(), {"feet": ["toe"]}), "feet names joint 'toe'"),
    ("rotations without a Skeleton", lambda: ((np.zeros((3, 3)), np.ones((3, 5, 4))), PARENTS, {}),
     "must then be a minimdm Skeleton"),
]  # fmt: skip


@pytest.mark.parametrize("make, match", [(b[1], b[2]) for b in BAD], ids=[b[0] for b in BAD])
def test_bad_input_is_refused_before_any_html(make, match, monkeypatch):
    def no_html(*args, **kwargs):
        raise AssertionError("HTML was made for bad input")

    monkeypatch.setattr(pmod, "Player", no_html)
    monkeypatch.setattr(pmod, "_poster", no_html)
    motions, parents, kwargs = make()
    with pytest.raises(ValueError, match=match):
        viz.player(motions, parents, **kwargs)


# --------------------------------------------------------------------------- the HTML


def lib_in(html):
    """The gzipped code a player's HTML carries, decoded (None when it carries none)."""
    m = re.search(r"LIB = (\{.*?\});", html)
    if m is None:
        assert "LIB = null" in html
        return None
    lib = json.loads(m.group(1))
    return {k: gzip.decompress(base64.b64decode(v)).decode() for k, v in lib.items()}


def payload_in(html):
    m = re.search(r'<script type="application/json" class="mmp-data">(.*?)</script>', html, re.S)
    return json.loads(m.group(1))


@pytest.fixture
def fresh_kernel(monkeypatch):
    """A kernel that has shown no player yet; ``where`` sets the (cell, count) being run."""
    state = {"embedded": False, "cell": None, "count": None}
    monkeypatch.setattr(pmod, "_KERNEL", state)
    where = {"now": (None, None)}
    monkeypatch.setattr(pmod, "_where", lambda: where["now"])
    return where


def test_code_is_carried_once_per_kernel_and_again_by_a_rerun(fresh_kernel):
    p = viz.player(walk(), PARENTS, poster=False)
    fresh_kernel["now"] = ("cell-a", 1)
    first = p._repr_html_()
    lib = lib_in(first)
    assert lib["three"] == (pmod.STATIC / "three.module.min.js").read_text()
    assert lib["player"] == (pmod.STATIC / "player.js").read_text()
    assert lib["player"].count('from "three"') == 1  # the one import the boot script rewrites
    assert len(first) > 200_000
    fresh_kernel["now"] = ("cell-a", 1)  # a second player in the same run of the same cell
    assert lib_in(p._repr_html_()) is None
    fresh_kernel["now"] = ("cell-b", 2)
    later = p._repr_html_()
    assert lib_in(later) is None and len(later) < 20_000
    fresh_kernel["now"] = ("cell-a", 3)  # cell a runs again: its old output will be replaced
    assert lib_in(p._repr_html_()) is not None
    assert lib_in(viz.player(walk(), PARENTS, poster=False, embed=True)._repr_html_())
    assert lib_in(viz.player(walk(), PARENTS, poster=False, embed=False)._repr_html_()) is None


def test_each_output_has_its_own_id_and_the_payload(fresh_kernel):
    x = walk()
    p = viz.player(x, PARENTS, labels=["</script><b>x"], poster=False)
    a, b = p._repr_html_(), p._repr_html_()
    ids = [re.search(r'class="minimdm-player" id="([^"]+)"', h).group(1) for h in (a, b)]
    assert ids[0] != ids[1] and f'ID = "{ids[1]}"' in b
    got = payload_in(b)
    assert got == p.payload and got["motions"][0]["label"] == "</script><b>x"
    np.testing.assert_allclose(pl.decode_positions(got["motions"][0], 5), x, atol=6e-4)
    assert "http://" not in a and "https://" not in a  # nothing from the network


def test_poster_is_a_small_png_and_save_stands_alone(tmp_path):
    p = viz.player([walk(), walk(seed=1)], PARENTS, labels=["a", "b"], targets=[[1.0, 0.0]])
    png = base64.b64decode(p.poster)
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) <= 30_000
    assert int.from_bytes(png[16:20], "big") == pmod.POSTER_WIDTH
    page = p.save(tmp_path / "p.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and lib_in(page) is not None
    assert 'class="mmp-poster"' in page
    # where the script does not run (an untrusted notebook), the still says how to play it;
    # the script's first act is to hide that note
    note = re.search(r'<div class="mmp-msg"[^>]*>([^<]*)</div>', page).group(1)
    assert note == pmod.STILL_NOTE and "Run this cell" in note
    assert 'querySelector(".mmp-msg").style.display = "none"' in page
    assert p.payload["follow"] is True  # the camera frames the characters by default
    with pytest.raises(ValueError, match="must end in .html"):
        p.save(tmp_path / "p.png")


def test_in_an_ipython_shell_a_rerun_of_the_first_cell_carries_the_code_again(monkeypatch):
    from IPython.core.interactiveshell import InteractiveShell

    monkeypatch.setattr(pmod, "_KERNEL", {"embedded": False, "cell": None, "count": None})
    shell = InteractiveShell.instance()
    try:
        outputs = []
        monkeypatch.setattr(shell.display_pub, "publish", lambda data, **kw: outputs.append(data))
        shell.user_ns.update(viz=viz, x=walk(), P=PARENTS)
        code = "display(viz.player(x, P, poster=False)); display(viz.player(x, P, poster=False))"
        carried = {}
        for run, cell in enumerate(["a", "a", "b", "a"]):
            outputs.clear()
            assert shell.run_cell(code, cell_id=cell, store_history=True).success
            carried[run] = [lib_in(o["text/html"]) is not None for o in outputs]
        assert carried == {0: [True, False], 1: [True, False], 2: [False, False], 3: [True, False]}
    finally:
        InteractiveShell.clear_instance()


def test_stored_notebooks_carry_the_current_player_code():
    # a chapter re-executed before player.js changed would publish the old player: its code key
    # (a hash of three.js + player.js) must be the current one
    import re
    from pathlib import Path

    from minimdm.viz.webplayer import _library

    key = _library()[0]
    stale = {}
    for nb in sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb")):
        keys = set(re.findall(r"minimdm-player-[0-9a-f]{12}", nb.read_text()))
        if keys - {key}:
            stale[nb.name] = sorted(keys - {key})
    assert not stale, f"re-execute these notebooks (their players carry old code): {stale}"
