"""The bundled Bandai-Namco corpus: unpacking, labels, the split by take, and bad input."""

import json
import shutil

import numpy as np
import pytest

from minimdm.motion import corpora
from minimdm.motion.bvh import BVHError, load_bvh
from minimdm.motion.skeleton import heading_angle


@pytest.fixture(scope="module")
def home(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    d = tmp_path_factory.mktemp("data")
    mp.setenv("MINIMDM_DATA", str(d))
    yield d
    mp.undo()


def test_unpacks_once_and_holds_every_take(home):
    folder = corpora.corpus_path("bandai-namco-1")
    assert folder == home / "bandai-namco-1"
    assert len(list((folder / "data").glob("*.bvh"))) == 174
    assert len(list((folder / "data").glob("*.json"))) == 174
    assert (folder / "LICENSE").exists()
    stamp = (folder / ".complete").stat().st_mtime_ns
    assert corpora.corpus_path("bandai-namco-1") == folder  # no second extraction
    assert (folder / ".complete").stat().st_mtime_ns == stamp


def test_a_partial_extraction_is_replaced(tmp_path, monkeypatch):
    monkeypatch.setenv("MINIMDM_DATA", str(tmp_path))
    partial = tmp_path / "bandai-namco-1" / "data"
    partial.mkdir(parents=True)
    (partial / "dataset-1_walk_normal_001.bvh").write_text("HIER")  # torn, no .complete
    folder = corpora.corpus_path("bandai-namco-1")
    assert (folder / ".complete").exists()
    assert (folder / "data" / "dataset-1_walk_normal_001.bvh").read_text().startswith("HIERARCHY")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folder left


def test_split_is_by_take_and_keeps_every_label_in_training(home):
    split = corpora.corpus_split("bandai-namco-1")
    train, test = set(split["train"]), set(split["test"])
    assert not train & test
    assert len(train | test) == 174 and 15 <= len(test) <= 30

    def labels(names):
        return {tuple(n.split("_")[1:3]) for n in names}

    contents = {c for c, _ in labels(test)}
    styles = {s for _, s in labels(test)}
    assert {c for c, _ in labels(train)} >= contents  # no content is only in the test set
    assert {s for _, s in labels(train)} >= styles
    assert len(styles) == 15  # every style is tested


def test_loaded_takes_carry_their_labels(home):
    takes = ["dataset-1_walk_happy_001", "dataset-1_bow_old_001"]
    ds = corpora.load_corpus("bandai-namco-1", takes=takes)
    assert ds.names == sorted(takes)
    assert ds["dataset-1_walk_happy_001"].labels == {"content": "walk", "style": "happy"}
    assert ds["dataset-1_bow_old_001"].labels == {"content": "bow", "style": "old"}
    walk = ds["dataset-1_walk_happy_001"]
    assert walk.fps == 30.0 and len(walk.skeleton) == 21
    # labels survive slicing and resampling
    assert walk.slice(3, 10).labels == walk.labels


def test_every_take_has_the_same_bones_in_metres(home, tmp_path):
    # The files are in centimetres with one skeleton. A per-take guess of the units made five
    # crouched or leaning takes (dashes, sad side steps) a third taller than the others.
    ds = corpora.load_corpus("bandai-namco-1")
    ref = ds["dataset-1_walk_normal_001"].skeleton.bone_lengths()
    for clip in ds:
        assert np.allclose(clip.skeleton.bone_lengths(), ref, atol=1e-5), clip.name
    dash = load_bvh(
        corpora.corpus_path("bandai-namco-1") / "data" / "dataset-1_dash_giant_001.bvh"
    )  # the guess alone
    assert dash.skeleton.bone_lengths().sum() > 1.2 * ref.sum()
    # in a folder, the crouched take takes the unit most of its files agree on
    folder = tmp_path / "mine"
    folder.mkdir()
    for take in ("dash_giant_001", "walk_normal_001", "run_sad_001"):
        shutil.copy(
            corpora.corpus_path("bandai-namco-1") / "data" / f"dataset-1_{take}.bvh", folder
        )
    for clip in load_bvh(folder):
        assert np.allclose(clip.skeleton.bone_lengths(), ref, atol=1e-5), clip.name
    thigh = ref[ds[0].skeleton.index("LowerLeg_L")]  # hip to knee
    assert 0.35 < thigh < 0.45


def test_heading_follows_the_walk(home):
    # The root's left axis is guessed from UpperLeg_L / UpperLeg_R (suffixes, not prefixes):
    # a walk faces where it goes, a walk backwards the other way.
    takes = ["dataset-1_walk_normal_001", "dataset-1_walk_sad_001", "dataset-1_walk-back_angry_001"]
    for clip in corpora.load_corpus("bandai-namco-1", takes=takes):
        F = clip.n_frames
        mid = np.arange(F // 4, 3 * F // 4)
        _, rot = clip.fk()
        heading = heading_angle(rot[mid, 0], clip.skeleton.lateral_axis).numpy()
        step = clip.root_pos[mid[-1], :2] - clip.root_pos[mid[0], :2]
        travel = np.arctan2(step[1], step[0])
        if clip.labels["content"] == "walk-back":
            travel += np.pi
        off = np.degrees(np.abs(np.angle(np.exp(1j * (heading - travel)))))
        assert np.median(off) < 15, (clip.name, np.median(off))


def test_bad_names_and_labels(home, tmp_path, monkeypatch):
    with pytest.raises(
        ValueError, match=r"known corpora: \['bandai-namco-1', 'bandai-namco-2', 'lafan1'\]"
    ):
        corpora.load_corpus("lafan2")
    with pytest.raises(ValueError, match="split must be"):
        corpora.load_corpus(split="validation")
    with pytest.raises(ValueError, match="are not in corpus"):
        corpora.load_corpus(takes=["dataset-1_fly_normal_001"])
    # a label file that contradicts its take's name is refused, naming both
    src = corpora.corpus_path("bandai-namco-1")
    fake = tmp_path / "bandai-namco-1"
    shutil.copytree(src / "cfg", fake / "cfg")
    (fake / "data").mkdir()
    take = "dataset-1_walk_happy_001"
    shutil.copy(src / "data" / f"{take}.bvh", fake / "data")
    (fake / "data" / f"{take}.json").write_text(json.dumps({"content": 1, "style": 1}))
    (fake / ".complete").write_text("")
    monkeypatch.setenv("MINIMDM_DATA", str(tmp_path))
    with pytest.raises(ValueError, match=r"'content': 'run'.*do not match.*walk_happy"):
        corpora.load_corpus(takes=[take])


def test_folder_with_mixed_skeletons_is_refused(home, tmp_path):
    src = corpora.corpus_path("bandai-namco-1") / "data"
    shutil.copy(src / "dataset-1_walk_normal_001.bvh", tmp_path / "a.bvh")
    text = (src / "dataset-1_run_normal_001.bvh").read_text()
    (tmp_path / "b.bvh").write_text(text.replace("JOINT Neck", "JOINT Throat"))
    with pytest.raises(BVHError, match=r"a.bvh and b.bvh .*'Neck'.*'Throat'"):
        load_bvh(tmp_path)


TINY_TRAIN = dict(
    width=32, depth=3, time_dim=8, T=4, batch_size=8, total_steps=4, rollout=2, teacher_steps=1,
    ramp_steps=1, eval_interval=2, ckpt_interval=0, log_interval=2, loop_frames=None,
)  # fmt: skip


def test_train_reads_a_corpus_name_or_a_bvh_folder(home, tmp_path, capsys):
    import yaml

    from minimdm.checkpoint import load_checkpoint
    from minimdm.cli import main

    takes = ["dataset-1_walk_normal_002", "dataset-1_run_sad_001"]
    assert set(takes) <= set(corpora.corpus_split("bandai-namco-1")["train"])
    # a corpus name with its split: trains on the named training takes, reports the test takes
    cfg = tmp_path / "corpus.yaml"
    cfg.write_text(
        yaml.safe_dump(dict(TINY_TRAIN, corpus="bandai-namco-1", split="train", clips=takes))
    )
    assert main(["train", str(cfg), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["steps"] == 4 and 0 <= summary["train_seconds"] <= summary["seconds"] + 0.1
    ck = load_checkpoint(tmp_path / "a")
    assert ck.metadata["data"]["corpus"] == "bandai-namco-1"
    assert sorted(ck.metadata["data"]["clips"]) == sorted(takes)
    log = [json.loads(ln) for ln in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log if "heldout_loss" in r] == [2, 4]
    # a folder of BVH files: the same two takes, no split, clip names from the file names
    folder = tmp_path / "mine"
    folder.mkdir()
    for t in takes:
        shutil.copy(corpora.corpus_path("bandai-namco-1") / "data" / f"{t}.bvh", folder)
    cfg = tmp_path / "folder.yaml"
    cfg.write_text(yaml.safe_dump(dict(TINY_TRAIN, corpus=str(folder))))
    assert main(["train", str(cfg), "--out", str(tmp_path / "b"), "--quiet"]) == 0
    ck = load_checkpoint(tmp_path / "b")
    assert ck.metadata["data"]["corpus"] == str(folder)
    assert sorted(ck.metadata["data"]["clips"]) == sorted(takes)
    log = [json.loads(ln) for ln in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert any("eval_loss" in r for r in log) and not any("heldout_loss" in r for r in log)


def test_bad_training_sources(home, tmp_path):
    with pytest.raises(ValueError, match=r"neither 'deepmimic', a known corpus .*bandai-namco-1"):
        corpora.load_motion("bandai-namco-9")
    with pytest.raises(ValueError, match="a BVH folder has no fixed split"):
        corpora.load_motion(str(tmp_path), split="train")
    with pytest.raises(ValueError, match="DeepMimic clips have no split"):
        corpora.load_motion("deepmimic", split="test")
    with pytest.raises(ValueError, match="not in corpus"):
        corpora.load_motion("bandai-namco-1", split="test", names=["dataset-1_walk_normal_002"])
