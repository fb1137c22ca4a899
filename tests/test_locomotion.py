"""The locomotion yardstick (minimdm.studies.locomotion) on a tiny model of the real skeleton."""

import dataclasses
from pathlib import Path

import pytest
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from minimdm.amdm.train import TrainConfig, train_amdm
from minimdm.checkpoint import load_checkpoint
from minimdm.studies.locomotion import (
    LOCOMOTION,
    LocomotionProtocol,
    locomotion_report,
    locomotion_takes,
    speed_curve,
)
from minimdm.validate import InputError, MismatchError

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    out = tmp_path_factory.mktemp("amdm")
    config = TrainConfig(
        width=32, depth=2, time_dim=16, T=4, batch_size=8, total_steps=2, teacher_steps=2,
        ramp_steps=0, eval_interval=0, ckpt_interval=0, eval_windows=8, corpus="bandai-namco-1",
        split="train", clips=["dataset-1_walk_normal_002"], loop_frames=None,
    )  # fmt: skip
    train_amdm(config, out, progress=False)
    return load_checkpoint(out)


def test_speed_curve_averages_the_root_speed_per_window():
    f = torch.zeros(2, 60, 9)
    f[0, :, 0] = 0.03  # 0.9 m/s forward at 30 fps
    f[1, :30, 1] = -0.04  # 1.2 m/s sideways, then standing
    curve = speed_curve(f, 30.0, 30)
    torch.testing.assert_close(curve, torch.tensor([[0.9, 0.9], [1.2, 0.0]]))


def test_the_report_covers_every_held_out_locomotion_take(ckpt):
    p = LocomotionProtocol(n_samples=2, seconds=1.0, long_seconds=2.0, tail_seconds=0.5)
    rep = locomotion_report(ckpt, p)
    takes = locomotion_takes("bandai-namco-1")
    assert [r["take"] for r in rep["takes"]] == list(takes.names) and len(takes) == 15
    assert list(rep["contents"]) == list(LOCOMOTION)
    assert sum(c["n_takes"] for c in rep["contents"].values()) == 15
    for r in rep["takes"]:
        assert r["take_speed"] > 0.3  # every take moves
        assert len(r["speed_by_second"]) == 2
        assert r["speed_ratio_10s"] == pytest.approx(r["speed_10s"] / r["take_speed"])
        assert 0.0 <= r["moving_60s"] <= 1.0
        assert r["FS"] >= 0 and r["FS_data"] > 0 and r["Bone.Err"] >= 0 and r["APD"] > 0
        assert 0.0 <= r["at_box_60s"] <= 1.0  # the model clamps to its training frames' range
    all_ = rep["all"]
    assert all_["worst_speed_ratio_10s"] <= all_["speed_ratio_10s"]
    assert all_["FS_ratio"] == pytest.approx(all_["FS"] / all_["FS_data"])
    from minimdm.studies.locomotion import pace_slope

    assert all_["pace_slope_10s"] == pace_slope(rep["contents"])  # over the six contents
    for r in rep["takes"]:  # shares of the last tail's frames nearest a locomotion take's
        for key in ("locomotion_10s", "locomotion_60s", "content_10s"):
            assert 0.0 <= r[key] <= 1.0
        assert r["content_10s"] <= r["locomotion_10s"]  # its own content is locomotion
        assert r["locomotion_data"] > 0.8  # the takes themselves look like locomotion
    assert all_["locomotion_data"] > 0.95 and 0.5 < all_["content_data"] < 1.0
    for r in rep["takes"]:  # whom the futures and the take resemble
        for when in ("10s", "60s", "data"):
            assert 0.0 <= r[f"style_{when}"] <= 1.0 and r[f"resembled_pace_{when}"] > 0
        # a held-out take moves at about the pace of the training takes its frames are nearest
        assert 0.5 < r["pace_vs_poses_data"] < 2.0
        assert r["pace_vs_poses_data"] == pytest.approx(r["take_speed"] / r["resembled_pace_data"])
    for when in ("10s", "60s"):  # the futures' distance off the data over the takes' own
        assert all_[f"off_data_{when}"] == pytest.approx(
            all_[f"pose_dist_{when}"] / all_["pose_dist_data"]
        )
        assert all(r[f"pose_dist_{when}"] > 0 for r in rep["takes"])
    groups = ("root", "positions", "velocities", "rotations")
    for g in groups:
        assert all_[f"off_data_10s_{g}"] == pytest.approx(
            all_[f"pose_dist_10s_{g}"] / all_[f"pose_dist_data_{g}"]
        )


def test_the_content_index_names_the_content_of_the_nearest_training_frame():
    """Training frames find themselves (their take's content, -1 for a gesture); a frame moved
    towards another take's frame takes that take's content once it is nearer to it."""
    from minimdm.motion.corpora import load_motion
    from minimdm.motion.features import encode
    from minimdm.studies.locomotion import ContentIndex

    index = ContentIndex("bandai-namco-1")
    assert set(index.labels.unique().tolist()) == {-1, *range(len(LOCOMOTION))}
    train = {c.name: c for c in load_motion("bandai-namco-1", split="train")}
    walk, bow = (
        encode(train["dataset-1_walk_normal_002"]),
        encode(train["dataset-1_bow_normal_001"]),
    )
    assert index.classify(walk[::10]).eq(LOCOMOTION.index("walk")).all()
    assert index.classify(bow[::10]).eq(-1).all()
    a, b = walk[20], bow[20]
    on_the_way = torch.stack([a + w * (b - a) for w in (0.02, 0.98)])
    assert index.classify(on_the_way).tolist() == [LOCOMOTION.index("walk"), -1]


def test_the_content_index_knows_the_take_of_each_frame_with_its_pace_and_style():
    """A training take's frames find their own take; its recorded pace is its mean ground speed;
    futures read against it score their speed over that pace and their share on its style."""
    from minimdm.motion.corpora import load_motion
    from minimdm.motion.features import encode
    from minimdm.studies.locomotion import ContentIndex, _resembled

    index = ContentIndex("bandai-namco-1")
    train = load_motion("bandai-namco-1", split="train")
    t = list(train.names).index("dataset-1_walk_sad_002")
    clip = train[t]
    feats = encode(clip)
    assert index.takes(feats[::10]).eq(t).all()
    speed = feats[:, 0:2].norm(dim=-1) * clip.fps
    assert float(index.take_pace[t]) == pytest.approx(float(speed.mean()), rel=1e-5)
    assert index.take_style[t] == "sad" and len(index.take_pace) == len(train)
    run = list(train.names).index("dataset-1_run_proud_001")
    near = torch.tensor([[t, t], [t, run]])  # two futures: a sad walk; half of it a proud run
    out = _resembled(index, near, torch.tensor([0.4, 1.0]), "sad", "10s")
    paces = index.take_pace
    assert out["resembled_pace_10s"] == pytest.approx(float(0.75 * paces[t] + 0.25 * paces[run]))
    expect = (0.4 / float(paces[t]) + 1.0 / float((paces[t] + paces[run]) / 2)) / 2
    assert out["pace_vs_poses_10s"] == pytest.approx(expect)
    assert out["style_10s"] == pytest.approx(0.75)  # 3 of the 4 frames are on a sad take


def test_the_held_in_diagnostic_starts_from_the_training_takes_long_enough(ckpt):
    """split='train' starts from the training takes instead, leaving out (and naming) those
    too short to start at start_frame; a split that does not exist is refused."""
    p = LocomotionProtocol(n_samples=1, seconds=0.5, long_seconds=0.0, tail_seconds=0.5)
    p = dataclasses.replace(p, split="train", start_frame=120)
    rep = locomotion_report(ckpt, p)
    train = locomotion_takes("bandai-namco-1", split="train")
    short = {c.name for c in train if c.n_frames <= 121}
    assert short and set(rep["skipped"]) == short
    assert [r["take"] for r in rep["takes"]] == [n for n in train.names if n not in short]
    assert not {r["take"] for r in rep["takes"]} & set(locomotion_takes("bandai-namco-1").names)
    assert rep["protocol"]["split"] == "train"
    with pytest.raises(InputError, match="split must be"):
        LocomotionProtocol(split="val")


def test_at_box_is_the_share_of_the_roots_features_on_the_clamps_edge(ckpt):
    """Root features pressed to the box count, in the denoiser's own normalized units; the
    joints do not."""
    from minimdm.diffusion import clip_bounds
    from minimdm.motion.features import Normalizer
    from minimdm.studies.locomotion import _on_box

    norm = Normalizer.from_dict(ckpt.normalizer)
    D = len(ckpt.normalizer["mean"])
    lo, hi = clip_bounds(ckpt.diffusion["clip_x0"], D)
    x = torch.zeros(3, 2, 5, D)  # normalized: each take's futures, 5 frames of the tail
    x[1, :, :, 0], x[1, :, :, 2] = hi[0], lo[2]  # two of the root's three features on the edge
    x[2, :, :, 3:] = hi[3:]  # only joints on the edge
    x[2, 0, :2, 1] = lo[1]  # and d_y on it in 2 of one future's 5 frames
    share = _on_box(ckpt, norm.denormalize(x))
    torch.testing.assert_close(share, torch.tensor([0.0, 2 / 3, 2 / 30], dtype=torch.float64))


def test_eta_reaches_the_ddim_sampler(ckpt):
    """With DDIM steps, ``eta`` changes the draws (eta 0 adds no noise after the first level),
    and the same protocol draws the same futures again."""
    p = LocomotionProtocol(n_samples=2, seconds=1.0, long_seconds=0.0, tail_seconds=0.5, steps=2)
    rows = [
        locomotion_report(ckpt, dataclasses.replace(p, eta=eta))["all"] for eta in (0.0, 1.0, 0.0)
    ]
    assert rows[0] == rows[2] and rows[0]["APD"] != rows[1]["APD"]


def test_a_checkpoint_of_another_skeleton_or_rate_is_named(ckpt):
    p = LocomotionProtocol(n_samples=1, seconds=1.0, long_seconds=0.0, tail_seconds=0.5)
    layout = dict(ckpt.feature_layout)
    other = dataclasses.replace(ckpt, metadata=dict(ckpt.metadata))
    other.metadata["feature_layout"] = layout | {"fps": 60.0}
    with pytest.raises(
        MismatchError, match="runs at 60 frames/s, but corpus 'bandai-namco-1'.* 30"
    ):
        locomotion_report(other, p)
    names = [f"J{i}" for i in range(len(layout["joint_names"]))]
    other.metadata["feature_layout"] = layout | {"joint_names": names}
    with pytest.raises(MismatchError, match=r"skeleton of 21 joints \(J0, .*\), but .* \(Hips"):
        locomotion_report(other, p)
    with pytest.raises(InputError, match="no labelled locomotion takes"):
        locomotion_report(ckpt, dataclasses.replace(p, corpus="deepmimic"))


@given(
    speeds=st.lists(st.floats(0.3, 4.0), min_size=2, max_size=6, unique=True),
    gain=st.floats(0.2, 5.0),
    power=st.floats(-1.0, 2.0),
)
def test_the_pace_kept_is_the_power_between_the_takes_speed_and_the_futures(speeds, gain, power):
    """Futures at ``gain * take_speed ** power`` keep the pace ``power``: 1 for any constant
    factor (a model a little fast everywhere still tells a dash from a walk), 0 for one pace."""
    from minimdm.studies.locomotion import pace_slope

    assume(max(speeds) / min(speeds) > 1.05)
    contents = {
        f"c{i}": {"take_speed": v, "speed_10s": gain * v**power} for i, v in enumerate(speeds)
    }
    assert pace_slope(contents) == pytest.approx(power, abs=1e-6)
    assert pace_slope({"walk": contents["c0"], "idle": {}}) is None  # one content with speeds
    assert pace_slope({}) is None


def test_the_study_grid_reads_the_pace_kept_from_rows_written_before_it(tmp_path):
    import json

    from minimdm.studies.locomotion import study_grid

    contents = {
        "walk": {"take_speed": 1.0, "speed_10s": 1.5},
        "dash": {"take_speed": 4.0, "speed_10s": 1.5},
    }
    old = {
        "name": "a",
        "protocol": {"seed": 0},
        "all": {"speed_ratio_10s": 1.0},
        "contents": contents,
    }
    new = {
        "name": "b",
        "protocol": {"seed": 0},
        "all": {"pace_slope_10s": 0.7},
        "contents": contents,
    }
    path = tmp_path / "study.jsonl"
    path.write_text(json.dumps(old) + "\n" + json.dumps(new) + "\n")
    grid = study_grid(path)
    assert grid["a"]["pace kept"] == pytest.approx(0.0)  # both end at 1.5 m/s: one pace
    assert grid["b"]["pace kept"] == 0.7  # a row that measured it keeps its own


def test_the_study_grid_pools_seeds_and_joins_table1(tmp_path):
    import json

    from minimdm.studies.locomotion import STUDY_COLUMNS, study_grid

    def loco(name, seed, speed):
        pool = {k: 1.0 for k in STUDY_COLUMNS.values()} | {"speed_ratio_10s": speed}
        return {"name": name, "protocol": {"seed": seed}, "all": pool}

    rows = [loco("a", 0, 0.8), loco("b", 0, 2.0), loco("a", 1, 1.2), loco("b", 0, 1.5),
            {"name": "a", "table1": {"APD": {"mean": 50.0, "std": 2.0}}}]  # fmt: skip
    path = tmp_path / "study.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    grid = study_grid(path)
    assert list(grid) == ["a", "b"]
    assert grid["a"]["speed 10 s"] == pytest.approx((1.0, 0.2))  # mean, std over seeds 0, 1
    assert grid["a"]["seeds"] == 2 and grid["a"]["T1 APD"] == (50.0, 2.0)
    assert grid["a"]["T1 ADE"] is None
    assert grid["b"]["speed 10 s"] == 1.5 and grid["b"]["seeds"] == 1  # the later row wins
    assert list(study_grid(path, ["b"])) == ["b"]
    with pytest.raises(ValueError, match="no row of the run 'c'"):
        study_grid(path, ["c"])
    from minimdm.studies.locomotion import study_table1  # the whole Table 1 record of a run

    assert study_table1(path, ["a"]) == {"a": {"APD": (50.0, 2.0)}}
    with pytest.raises(ValueError, match="no Table 1 row of the run 'b'"):
        study_table1(path, ["b"])


def test_study_contents_pools_one_number_per_content_over_seeds(tmp_path):
    import json

    from minimdm.studies.locomotion import study_contents

    def loco(name, seed, walk, run):
        contents = {"walk": {"speed_ratio_10s": walk}, "run": {"speed_ratio_10s": run}}
        return {"name": name, "protocol": {"seed": seed}, "all": {}, "contents": contents}

    rows = [loco("a", 0, 1.0, 0.4), loco("a", 1, 1.4, 0.6), loco("b", 0, 2.0, 0.5)]
    path = tmp_path / "study.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    table = study_contents(path, ["b", "a"], contents=("walk", "run"))
    assert list(table) == ["b", "a"]
    assert table["a"]["walk"] == pytest.approx((1.2, 0.2))
    assert table["a"]["run"] == pytest.approx((0.5, 0.1))
    assert table["b"] == {"walk": 2.0, "run": 0.5}
    with pytest.raises(ValueError, match="no yardstick row of the run 'c'"):
        study_contents(path, ["c"])


def test_the_yardstick_table_pools_one_tag_per_content_and_model(tmp_path):
    import json

    from minimdm.studies.locomotion import YARDSTICK_COLUMNS, yardstick_table

    def rec(ck, scope, content, seed, speed, tag="new"):
        r = {"checkpoint": ck, "scope": scope, "tag": tag, "protocol": {"seed": seed}}
        r |= {k: 1.0 for k in YARDSTICK_COLUMNS.values()} | {"speed_ratio_10s": speed}
        return r | ({"content": content} if scope == "content" else {})

    rows = [rec("m", "content", "walk", 0, 0.5), rec("m", "content", "walk", 1, 0.7),
            rec("m", "all", None, 0, 0.9), rec("m", "content", "walk", 0, 9.0, tag="old"),
            rec("m", "take", "walk", 0, 9.0)]  # fmt: skip
    path = tmp_path / "loco.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    table = yardstick_table(path, "new", {"A-MDM": "m"}, contents=("walk",))
    assert list(table) == ["walk, A-MDM", "all, A-MDM"]
    assert table["walk, A-MDM"]["speed 10 s"] == pytest.approx((0.6, 0.1))
    assert table["walk, A-MDM"]["seeds"] == 2 and table["all, A-MDM"]["seeds"] == 1
    mine = yardstick_table(path, "new", {"A-MDM": "m"}, ("walk",), {"pace": "speed_ratio_10s"})
    assert list(mine["walk, A-MDM"]) == ["pace", "seeds"]  # chosen columns, in order
    assert mine["walk, A-MDM"]["pace"] == pytest.approx((0.6, 0.1))
    with pytest.raises(ValueError, match="no 'new' row of m for 'run'"):
        yardstick_table(path, "new", {"A-MDM": "m"}, contents=("run",))


def test_an_aamdm_motion_model_runs_the_same_yardstick(tmp_path):
    """An AAMDM motion checkpoint goes through its own rollout (trajectory features and latent
    diffusion) from the same takes and frames, and reports the same columns."""
    from minimdm.aamdm.motion_train import AAMDMTrainConfig, train_aamdm_motion

    cfg = AAMDMTrainConfig(
        corpus="bandai-namco-1", split="train", clips=["dataset-1_walk_normal_002"],
        loop_frames=None, z_dim=4, ae_width=16, ae_depth=2, ae_steps=2, ae_batch=8, latent_dim=2,
        width=16, depth=2, disc_width=16, window=2, polish_steps=1, polish_batch=4, gan_steps=1,
        gan_batch=4,
    )  # fmt: skip
    train_aamdm_motion(cfg, tmp_path, progress=False)
    ck = load_checkpoint(tmp_path)
    assert ck.kind == "aamdm_motion"
    p = LocomotionProtocol(n_samples=2, seconds=1.0, long_seconds=0.0, tail_seconds=0.5)
    rep = locomotion_report(ck, p)
    assert [r["take"] for r in rep["takes"]] == list(locomotion_takes("bandai-namco-1").names)
    for r in rep["takes"]:
        assert r["speed_10s"] >= 0 and r["FS"] >= 0 and r["Bone.Err"] >= 0 and r["APD"] >= 0
        assert r["FS_data"] > 0 and len(r["speed_by_second"]) == 1


def test_the_noise_probe_correlates_each_frame_with_the_last_and_keeps_unit_variance(monkeypatch):
    """benchmarks/amdm_noise_probe.py: a frame's noise is rho * the last one's + fresh noise."""
    import importlib

    from minimdm.amdm import sampling

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
    probe = importlib.import_module("amdm_noise_probe")
    tapes = []
    monkeypatch.setattr(sampling.Sampler, "frame", lambda self, c, g=None, **kw: tapes.append(g))
    probe.correlated_frames(0.8)  # wraps the recorder (monkeypatch restores the original after)

    class Fake:  # what the wrapper reads of a Sampler: its schedule's T
        schedule = type("S", (), {"T": 4})()

    g = torch.Generator().manual_seed(0)
    cond = torch.zeros(400, 30)
    for _ in range(3):
        sampling.Sampler.frame(Fake(), cond, g)
    a, b, c = (t.noise for t in tapes)
    assert a.shape == (400, 30 * 5)
    for x, y in ((a, b), (b, c)):
        r = torch.corrcoef(torch.stack([x.flatten(), y.flatten()]))[0, 1]
        assert abs(r - 0.8) < 0.02 and abs(y.std() - 1) < 0.02


def test_one_step_pace_draws_from_the_recorded_frame_before_each_frame(ckpt, monkeypatch):
    """With a model that repeats its condition, the one-step speed is the recorded speed of the
    frame before each one: the pace is read on the right frames, per content and for all."""
    from minimdm.amdm.sampling import Sampler
    from minimdm.motion.features import encode
    from minimdm.studies.locomotion import one_step_pace

    monkeypatch.setattr(Sampler, "frame", lambda self, cond, generator=None: cond.clone())
    pace = one_step_pace(ckpt, "bandai-namco-1", n_samples=2)
    takes = locomotion_takes("bandai-namco-1")
    assert list(pace) == list(LOCOMOTION) + ["all"]
    for content in LOCOMOTION:
        speeds = [encode(c)[:, :2].norm(dim=-1) for c in takes if c.labels["content"] == content]
        before = torch.cat([s[:-1] for s in speeds]).double().mean() * 30
        after = torch.cat([s[1:] for s in speeds]).double().mean() * 30
        row = pace[content]
        assert row["one_step_speed"] == pytest.approx(float(before), rel=1e-4)
        assert row["take_speed"] == pytest.approx(float(after), rel=1e-4)
        assert row["one_step_ratio"] == pytest.approx(float(before / after), rel=1e-4)
    assert 0.9 < pace["all"]["one_step_ratio"] < 1.1  # the recording keeps its own pace


def test_off_the_data_is_the_distance_to_the_nearest_training_frame_over_the_takes():
    """A training frame is at distance 0 from the index; a frame moved off it by one spread in
    every feature is at most 1 away (the distance is the RMS over features, in spreads); the
    held-out takes' own frames sit close but not on it."""
    from minimdm.motion.corpora import load_motion
    from minimdm.motion.features import encode
    from minimdm.studies.locomotion import ContentIndex

    index = ContentIndex("bandai-namco-1")
    train = {c.name: c for c in load_motion("bandai-namco-1", split="train")}
    walk = encode(train["dataset-1_walk_normal_002"])[::10]
    labels, dist = index.nearest(walk)
    assert torch.equal(labels, index.classify(walk)) and dist.shape == labels.shape
    assert dist.max() < 1e-3
    _, moved = index.nearest(walk + index.std)  # one spread off in every feature
    assert (moved > 0.2).all() and (moved <= 1.0 + 1e-4).all()
    held_out = encode(load_motion("bandai-namco-1", split="test")[0])
    _, own = index.nearest(held_out)
    assert 0 < float(own.mean()) < float(moved.mean())
    labels, gap = index.gaps(walk + index.std)  # the difference from the nearest frame
    assert gap.shape == walk.shape
    torch.testing.assert_close(gap.pow(2).mean(-1).sqrt(), moved)
    from minimdm.motion.features import FeatureLayout
    from minimdm.studies.locomotion import _feature_groups

    names = train["dataset-1_walk_normal_002"].skeleton.names
    groups = _feature_groups(FeatureLayout(tuple(names)))
    cover = sorted(i for cols in groups.values() for i in range(walk.shape[1])[cols])
    assert cover == list(range(walk.shape[1]))  # the groups split the features, once each
