"""The command line and the evaluation protocol, end to end on a tiny model of two real clips."""

import json

import numpy as np
import pytest
import torch
import yaml

import minimdm
from minimdm.amdm import evaluation
from minimdm.checkpoint import load_checkpoint
from minimdm.cli import main
from minimdm.motion import bvh, features

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

pytest.importorskip("pybullet_data")

TINY = dict(
    model_kind="amdm",
    width=32,
    depth=3,
    time_dim=16,
    T=4,
    predicts="x0",
    batch_size=16,
    total_steps=12,
    rollout=2,
    teacher_steps=4,
    ramp_steps=4,
    eval_interval=0,
    ckpt_interval=0,
    log_interval=4,
    clips=["walk", "kick"],
    loop_frames=90,
)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny A-MDM trained by `minimdm train` on two clips."""
    root = tmp_path_factory.mktemp("cli")
    cfg = root / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(TINY))
    out = root / "ckpt"
    assert main(["train", str(cfg), "--out", str(out), "--set", "seed=3", "--quiet"]) == 0
    return cfg, out


def test_train_records_config_and_command_and_resumes(trained, capsys):
    cfg, out = trained
    ck = load_checkpoint(out)
    assert ck.step == TINY["total_steps"]
    assert ck.config["seed"] == 3 and ck.config["width"] == 32
    assert ck.metadata["command"].startswith("minimdm train ")
    assert "--set seed=3" in ck.metadata["command"]
    before = out.joinpath("model.safetensors").read_bytes()
    capsys.readouterr()
    # Same command again: resumes at the last step and trains no further.
    assert main(["train", str(cfg), "--out", str(out), "--set", "seed=3", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["steps"] == TINY["total_steps"]
    assert out.joinpath("model.safetensors").read_bytes() == before
    # A changed config refuses to resume into the same folder.
    assert main(["train", str(cfg), "--out", str(out), "--set", "seed=4", "--quiet"]) == 2


def test_sample_writes_npz_bvh_and_gif(trained, tmp_path):
    _, out = trained
    npz = tmp_path / "m.npz"
    assert main(["sample", "--checkpoint", str(out), "--frames", "20", "--out", str(npz),
                 "--start", "kick:5", "--quiet"]) == 0  # fmt: skip
    arr = np.load(npz)
    assert arr["positions"].shape == (20, 15, 3)
    assert np.isfinite(arr["positions"]).all()
    bvh_path = tmp_path / "m.bvh"
    assert main(["sample", "--checkpoint", str(out), "--frames", "12", "--out", str(bvh_path),
                 "--quiet"]) == 0  # fmt: skip
    clip = bvh.load_bvh(bvh_path, fps=None)
    assert clip.n_frames == 12 and len(clip.skeleton) == 15
    gif = tmp_path / "m.gif"
    assert main(["sample", "--checkpoint", str(out), "--frames", "6", "--out", str(gif),
                 "--samples", "2", "--quiet"]) == 0  # fmt: skip
    assert gif.stat().st_size > 1000


def test_sample_rejects_bad_arguments(trained, tmp_path, capsys):
    _, out = trained
    argv = ["sample", "--checkpoint", str(out), "--frames", "5", "--out", str(tmp_path / "x.txt")]
    assert main(argv) == 2
    assert "minimdm sample: error: --out must end in .npz, .bvh" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:  # argparse: exit code 2, the usual prefix
        main(
            ["sample", "--checkpoint", str(out), "--frames", "0", "--out", str(tmp_path / "x.npz")]
        )
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert (
        "minimdm sample: error: argument --frames: must be an integer in [1, 1000000], got 0" in err
    )
    assert main(["sample", "--checkpoint", str(tmp_path / "none"), "--frames", "5",
                 "--out", str(tmp_path / "x.npz")]) == 2  # fmt: skip


def test_eval_json_has_every_table1_metric(trained, capsys):
    _, out = trained
    capsys.readouterr()
    args = ["eval", "--checkpoint", str(out), "--json", "--states", "2", "--samples", "3"]
    assert main([*args, "--seeds", "2"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert set(evaluation.TABLE1_COLUMNS) <= set(row)
    assert row["protocol"]["n_samples"] == 3 and row["unit"] == "cm"
    assert row["APD"]["mean"] > 0 and row["APD"]["std"] >= 0


def test_states_come_with_the_right_ground_truth(trained):
    ck = load_checkpoint(trained[1])
    clips = evaluation.checkpoint_clips(ck)
    states = evaluation.random_states(clips, 5, ref_frames=30, seed=1)
    for s in states:
        clip = clips[s.clip]
        assert np.array_equal(s.reference, clip.positions[s.frame + 1 : s.frame + 31])
        # x_0 describes clip frame s.frame: decoding the next true frame from its start pose
        # lands on that frame.
        feats = features.encode(clip)
        pos = features.decode(feats[s.frame : s.frame + 1].double(), s.start_pose)
        assert torch.allclose(pos[0].float(), torch.as_tensor(s.reference[0]), atol=1e-3)
    again = evaluation.random_states(clips, 5, ref_frames=30, seed=1)
    assert [(s.clip, s.frame) for s in again] == [(s.clip, s.frame) for s in states]
    raw = evaluation.checkpoint_clips(ck, unrolled=False)
    for s in evaluation.continuation_states(raw, per_clip=2):
        assert raw[s.clip].n_frames - 30 <= s.frame < raw[s.clip].n_frames


def test_dataset_row_has_rigid_bones_and_drift_is_measured(trained):
    ck = load_checkpoint(trained[1])
    sk = evaluation.checkpoint_skeleton(ck)
    row = evaluation.dataset_row(evaluation.checkpoint_clips(ck), sk)
    assert row["Bone.Err"][0] < 1e-3  # motion capture through FK: bones are rigid
    assert row["Jnt.Accel"][0] > 0
    state = evaluation.initial_state(ck, "walk", 3)
    d = evaluation.drift(ck, state, n_frames=40, n_samples=2, window=10)
    assert d["frame"].tolist() == [10, 20, 30, 40]
    assert np.isfinite(d["bone_err"]).all() and (d["root_height"] > 0).all()
    assert (d["root_speed"] >= 0).all() and d["root_speed"].shape == (4,)


def test_format_table_and_pretrained_errors(tmp_path, monkeypatch):
    text = evaluation.format_table({"a": {"APD": (1.234, 0.5)}, "b": {"FS": 2.0}})
    lines = text.splitlines()
    assert lines[0].split() == ["model", "APD", "FS"]
    assert "1.23 ± 0.50" in lines[1] and lines[1].rstrip().endswith("-")
    ckpts, configs = tmp_path / "checkpoints", tmp_path / "configs"
    (ckpts / "family" / "T5").mkdir(parents=True)
    (ckpts / "family" / "T5" / "model.safetensors").touch()
    configs.mkdir()
    (configs / "amdm_x.yaml").touch()
    (configs / "aamdm_x.yaml").touch()
    monkeypatch.setattr(minimdm, "CHECKPOINT_DIR", ckpts)
    with pytest.raises(FileNotFoundError, match=r"available: \['family/T5'\]\. Each shipped"):
        minimdm.pretrained("nope")
    with pytest.raises(FileNotFoundError, match="Make it with: minimdm train configs/amdm_x.yaml"):
        minimdm.pretrained("amdm_x")
    with pytest.raises(FileNotFoundError, match=r"python -m minimdm\.aamdm train configs/aamdm_x"):
        minimdm.pretrained("aamdm_x")
