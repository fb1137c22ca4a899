"""Nothing is lost: atomic writes, one run per output folder, run folders outside the shipped
checkpoints, downloads that keep nothing they cannot trust, and an exact resume after kill -9.

Every training here is a few steps of a tiny network, so the module takes seconds; processes are
started only where a second process is the point (a live lock holder, a run killed by SIGKILL).
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import minimdm
from minimdm import files
from minimdm.amdm.train import train_amdm
from minimdm.amdm.train_config import TrainConfig
from minimdm.checkpoint import load_checkpoint, load_train_state
from minimdm.cli import main
from minimdm.files import LOCK_NAME, LockedError, RunLock, WriteError, atomic_output, atomic_write

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

ROOT = Path(__file__).resolve().parents[1]

FEATS = [np.sin(np.arange(40)[:, None] * (0.1 + 0.05 * np.arange(8))).astype(np.float32)]
"""A tiny training set: one clip of 8 smooth features (the process a test kills loads it too)."""


def tiny(**kw) -> TrainConfig:
    base = dict(width=16, depth=2, time_dim=8, T=2, batch_size=4, total_steps=2, rollout=1,
                teacher_steps=1, ramp_steps=1, eval_interval=0, ckpt_interval=0, log_interval=1,
                eval_windows=4)  # fmt: skip
    return TrainConfig(**{**base, **kw})


BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 100 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 30 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0 30 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 10 0
      }
    }
  }
  JOINT LeftFoot
  {
    OFFSET 10 -90 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 -5 0
    }
  }
}
MOTION
Frames: 16
Frame Time: 0.0333333
"""


def write_corpus(folder: Path) -> Path:
    """A folder with one 16-frame BVH take of a swaying 4-joint body (centimetres)."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = [
        " ".join(
            f"{v:.4f}"
            for v in (
                3 * i,
                100,
                0,
                5 * np.sin(i / 3),
                0,
                0,
                4 * np.sin(i / 2),
                0,
                0,
                2 * np.cos(i / 4),
                0,
                0,
                10 * np.sin(i / 3),
                0,
                0,
            )
        )  # fmt: skip
        for i in range(16)
    ]
    (folder / "sway.bvh").write_text(BVH + "\n".join(rows) + "\n")
    return folder


def full_disk(f, data):
    """files._write that fills the disk half-way, as a full disk does."""
    f.write(data[: len(data) // 2])
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def names(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()}


# --------------------------------------------------------------------------------------------
# Atomic writes


def test_a_full_disk_leaves_the_old_file_and_no_temporary_file(tmp_path, monkeypatch):
    target = tmp_path / "log.jsonl"
    atomic_write(target, "old\n")
    monkeypatch.setattr(files, "_write", full_disk)
    with pytest.raises(WriteError, match=r"cannot write .*log\.jsonl: No space left") as e:
        atomic_write(target, "new, longer text\n" * 100)
    assert e.value.errno == errno.ENOSPC
    assert target.read_text() == "old\n" and names(tmp_path) == {"log.jsonl"}


def test_a_writer_that_fails_half_way_leaves_nothing(tmp_path):
    target = tmp_path / "walk.npz"
    with pytest.raises(WriteError, match="walk.npz"):
        with atomic_output(target) as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".npz"
            tmp.write_bytes(b"half a file")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert names(tmp_path) == set()
    with atomic_output(target) as tmp:  # numpy keeps the name: the suffix is already .npz
        np.savez_compressed(tmp, x=np.arange(3))
    assert np.load(target)["x"].tolist() == [0, 1, 2] and names(tmp_path) == {"walk.npz"}


def test_a_bug_in_a_writer_keeps_its_traceback_and_leaves_nothing(tmp_path):
    with pytest.raises(ZeroDivisionError):
        with atomic_output(tmp_path / "x.gif") as tmp:
            tmp.write_bytes(b"GIF8")
            1 / 0  # noqa: B018
    assert names(tmp_path) == set()


# --------------------------------------------------------------------------------------------
# One run per folder

HOLD = textwrap.dedent(
    """
    import sys
    from minimdm.files import RunLock
    with RunLock(sys.argv[1], "minimdm train other.yaml"):
        print("holding", flush=True)
        sys.stdin.read()  # until the test closes our stdin
    """
)


@pytest.fixture
def holder(tmp_path):
    """Another live process that holds the lock of ``tmp_path / "run"``."""
    folder = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env=env)  # fmt: skip
    try:
        assert proc.stdout.readline().strip() == "holding"
        yield folder, proc.pid
    finally:
        proc.stdin.close()
        proc.wait(timeout=60)


def test_a_second_live_run_is_refused_naming_the_first(holder, capsys):
    folder, pid = holder
    with pytest.raises(LockedError, match=rf"in use by another run \(pid {pid} on .*started .*"
                       r"command: minimdm train other.yaml\)"):  # fmt: skip
        train_amdm(tiny(), folder, FEATS, progress=False)
    assert names(folder) == {LOCK_NAME}  # nothing trained, nothing written
    cfg = folder.parent / "tiny.yaml"
    cfg.write_text("T: 2\n")
    assert main(["train", str(cfg), "--out", str(folder), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("minimdm train: error: ") and f"pid {pid}" in err
    assert len(err.splitlines()) == 1


def test_the_lock_goes_with_the_run_and_a_dead_runs_lock_is_taken_over(tmp_path):
    folder = tmp_path / "run"
    train_amdm(tiny(), folder, FEATS, progress=False)
    assert LOCK_NAME not in names(folder)  # released at the end
    dead = {"pid": 999_999_999, "host": __import__("socket").gethostname(),
            "started": "2026-01-01T00:00:00", "command": "minimdm train killed.yaml"}  # fmt: skip
    (folder / LOCK_NAME).write_text(json.dumps(dead))
    with pytest.warns(UserWarning, match=r"took over the lock .*pid 999999999.*killed\.yaml"):
        train_amdm(tiny(total_steps=3), folder, FEATS, progress=False)
    assert load_train_state(folder)[1]["step"] == 3 and LOCK_NAME not in names(folder)


def test_the_lock_is_reentrant_and_only_rank_0_takes_it(tmp_path, monkeypatch):
    with RunLock(tmp_path, "outer"):
        with RunLock(tmp_path, "inner"):  # a trainer calling a trainer on the same folder
            assert json.loads((tmp_path / LOCK_NAME).read_text())["command"] == "outer"
        assert (tmp_path / LOCK_NAME).exists()
    assert not (tmp_path / LOCK_NAME).exists()
    monkeypatch.setenv("RANK", "1")  # torchrun: rank 0 alone writes, and locks
    with RunLock(tmp_path / "r1"):
        assert not (tmp_path / "r1").exists()


def test_a_lock_of_another_machine_is_not_taken_over(tmp_path):
    other = {"pid": 1, "host": "elsewhere", "started": "2026-01-01", "command": "minimdm rl x"}
    (tmp_path / LOCK_NAME).write_text(json.dumps(other))
    with pytest.raises(LockedError, match=r"pid 1 on elsewhere.*delete .*run\.lock"):
        with RunLock(tmp_path):
            pass
    assert json.loads((tmp_path / LOCK_NAME).read_text()) == other


KILLED = textwrap.dedent(
    """
    import os, signal, sys
    import importlib.util
    from minimdm.amdm.train import train_amdm

    spec = importlib.util.spec_from_file_location("nothing_lost", sys.argv[2])
    here = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(here)  # this test module: FEATS and tiny()
    FEATS, tiny = here.FEATS, here.tiny

    def kill(step, record):
        if step == 3:  # right after the checkpoint of step 3
            os.kill(os.getpid(), signal.SIGKILL)

    train_amdm(tiny(total_steps=5, ckpt_interval=3), sys.argv[1], FEATS, progress=False,
               callback=kill, num_threads=1)
    """
)


def test_kill_9_then_resume_is_bit_exact_and_takes_over_the_lock(tmp_path):
    """A run killed by SIGKILL leaves its lock file; the next run takes it over, resumes from
    the last checkpoint and ends with the very weights of an uninterrupted run."""
    full, cut = tmp_path / "full", tmp_path / "cut"
    train_amdm(tiny(total_steps=5, ckpt_interval=3), full, FEATS, progress=False)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-c", KILLED, str(cut), __file__], env=env,
                       capture_output=True, text=True, timeout=300)  # fmt: skip
    assert r.returncode == -signal.SIGKILL, r.stderr[-2000:]
    assert (cut / LOCK_NAME).exists() and load_train_state(cut)[1]["step"] == 3
    with pytest.warns(UserWarning, match="took over the lock"):
        train_amdm(tiny(total_steps=5, ckpt_interval=3), cut, FEATS, progress=False)
    _, a = load_train_state(full)
    _, b = load_train_state(cut)
    assert a["step"] == b["step"] == 5
    for part in ("model", "ema"):
        for k in a[part]:
            assert torch.equal(a[part][k], b[part][k]), (part, k)
    assert torch.equal(a["generator"], b["generator"])


# --------------------------------------------------------------------------------------------
# Run folders: runs/ by default, the shipped checkpoints only with --ship


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A working folder with a tiny BVH corpus and config, and a stand-in for the shipped
    checkpoints (minimdm.CHECKPOINT_DIR), so that no test writes near the real ones."""
    corpus = write_corpus(tmp_path / "corpus")
    config = tmp_path / "configs" / "tiny.yaml"
    config.parent.mkdir()
    config.write_text(yaml.safe_dump(dict(tiny().__dict__, corpus=str(corpus), split=None,
                                          clips=None, config_file=None)))  # fmt: skip
    shipped = tmp_path / "checkpoints"
    (shipped / "tiny").mkdir(parents=True)
    (shipped / "tiny" / "model.json").write_text('{"shipped": true}\n')
    monkeypatch.setattr(minimdm, "CHECKPOINT_DIR", shipped)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_training_writes_to_runs_by_default(project, capsys):
    assert main(["train", "configs/tiny.yaml", "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out)["checkpoint"]
    assert Path(out) == Path("runs/tiny/model.safetensors")
    assert load_checkpoint(project / "runs" / "tiny").metadata["command"] == (
        "minimdm train configs/tiny.yaml"
    )
    assert (project / "checkpoints" / "tiny" / "model.json").read_text() == '{"shipped": true}\n'


def test_sample_on_a_full_disk_is_one_line_naming_the_file(project, monkeypatch, capsys):
    """`minimdm sample` on a full disk: one line, exit 2, no file and no temporary file."""
    assert main(["train", "configs/tiny.yaml", "--quiet"]) == 0
    out = project / "out"
    out.mkdir()
    monkeypatch.setattr(files, "_write", full_disk)  # what atomic_write writes with (BVH)

    def savez_on_a_full_disk(path, **arrays):  # numpy writes .npz itself
        Path(path).write_bytes(b"PK\x03\x04 half a zip")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(np, "savez_compressed", savez_on_a_full_disk)
    capsys.readouterr()
    for name in ("walk.bvh", "walk.npz"):
        code = main(["sample", "--checkpoint", "runs/tiny", "--frames", "3", "--quiet",
                     "--out", str(out / name)])  # fmt: skip
        err = capsys.readouterr().err.strip()
        assert code == 2, err
        assert err == f"minimdm sample: error: cannot write {out / name}: No space left on device"
    assert names(out) == set()


@pytest.mark.parametrize(
    "spelling",
    ["checkpoints/tiny", "{root}/checkpoints/tiny", "runs/../checkpoints/tiny", "link/tiny",
     "checkpoints/new", "checkpoints"],
)  # fmt: skip
def test_a_shipped_folder_is_refused_however_it_is_spelled(project, capsys, spelling):
    (project / "link").symlink_to(project / "checkpoints")
    out = spelling.format(root=project)
    assert main(["train", "configs/tiny.yaml", "--out", out, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("minimdm train: error: --out") and "--ship" in err, err
    assert "shipped checkpoints" in err and len(err.splitlines()) == 1
    assert names(project / "checkpoints" / "tiny") == {"model.json"}
    assert not (project / "checkpoints" / "new").exists()


def test_ship_writes_the_shipped_checkpoint_and_records_it(project, capsys):
    assert main(["train", "configs/tiny.yaml", "--ship", "--quiet"]) == 0
    ck = load_checkpoint(project / "checkpoints" / "tiny")
    assert ck.metadata["command"] == "minimdm train configs/tiny.yaml --ship"
    assert main(["train", "configs/tiny.yaml", "--ship", "--out", "checkpoints/tiny/T5",
                 "--set", "T=5", "--quiet"]) == 0  # fmt: skip
    ck = load_checkpoint(project / "checkpoints" / "tiny" / "T5")
    assert ck.metadata["command"] == (
        "minimdm train configs/tiny.yaml --set T=5 --out checkpoints/tiny/T5 --ship"
    )
    assert not (project / "runs").exists()


def test_the_aamdm_command_shares_the_run_folder_rules(project, capsys):
    from minimdm.cli import aamdm_main

    (project / "configs" / "aamdm_tiny.yaml").write_text("ae_steps: 1\n")
    assert aamdm_main(["train", "configs/aamdm_tiny.yaml", "--out", "checkpoints/x"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m minimdm.aamdm train: error: --out") and "--ship" in err


def test_every_shipped_checkpoint_records_its_command():
    for meta in sorted((ROOT / "checkpoints").glob("*/model.json")):
        command = json.loads(meta.read_text()).get("command")
        assert command and command.split()[0] in ("minimdm", "python"), meta


def test_every_shipped_checkpoints_readable_metadata_is_its_weights_files_own():
    """The loader reads the metadata inside the weights file and warns when model.json beside it
    differs: a hand edit of one copy alone (say, of the recorded command) would not be seen."""
    for meta in sorted((ROOT / "checkpoints").glob("*/model.json")):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            ck = load_checkpoint(meta.parent)
        assert ck.metadata == json.loads(meta.read_text()), meta


def test_the_readme_and_configs_show_how_to_remake_a_shipped_checkpoint():
    """Each command that writes a shipped checkpoint says --ship; no other claims to."""
    readme = (ROOT / "README.md").read_text()
    for line in readme.splitlines():
        if "-> checkpoints/" in line and not line.lstrip().startswith("minimdm export"):
            assert "--ship" in line, line
    shipped = {p.name for p in (ROOT / "checkpoints").iterdir() if p.is_dir()}
    for config in sorted((ROOT / "configs").glob("*.yaml")):
        header = "\n".join(ln for ln in config.read_text().splitlines() if ln.startswith("#"))
        if config.stem in shipped:
            assert "--ship" in header and f"checkpoints/{config.stem}/" in header, config.name
        else:
            assert "-> checkpoints/" not in header or "--ship" in header, config.name
