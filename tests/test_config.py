"""The one config loader: YAML or TOML into a dataclass, unknown keys named, types converted."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from minimdm import cli
from minimdm.aamdm.motion_train import AAMDMTrainConfig
from minimdm.amdm.train import TrainConfig
from minimdm.config import from_dict, load_config, with_changes

ROOT = Path(__file__).resolve().parents[1]
BOOK = str(ROOT / "configs" / "amdm.yaml")


@dataclass
class Run:
    """A small config with every kind of field the trainers use."""

    lr: float = 1e-3
    steps: int = 10
    name: str = "run"
    clip_x0: float | None = 5.0
    clips: list[str] | None = None
    horizons: list[int] = field(default_factory=lambda: [10, 20])
    ema: bool = True
    config_file: str | None = None


def test_yaml_and_toml_load_the_same_config(tmp_path):
    y = tmp_path / "run.yaml"
    y.write_text("lr: 5e-4\nsteps: 30\nclip_x0: null\nclips: [walk, run]\nhorizons: [5, 15]\n")
    t = tmp_path / "run.toml"
    t.write_text('lr = 5e-4\nsteps = 30\nclips = ["walk", "run"]\nhorizons = [5, 15]\n')
    a, b = load_config(y, Run), load_config(t, Run)
    assert a.lr == b.lr == 5e-4 and isinstance(a.lr, float)  # YAML 1.1 read "5e-4" as a string
    assert a.steps == b.steps == 30 and a.clips == b.clips == ["walk", "run"]
    assert a.horizons == b.horizons == [5, 15]
    assert a.clip_x0 is None and b.clip_x0 == 5.0  # TOML has no null: the default stays
    assert a.config_file == y.as_posix() and b.config_file == t.as_posix()
    y.write_text("config_file: elsewhere.yaml\n")
    assert load_config(y, Run).config_file == "elsewhere.yaml"
    y.write_text("")
    assert load_config(y, Run) == Run(config_file=y.as_posix())


def test_unknown_keys_are_named_with_the_file_and_the_known_keys(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("lr: 1e-3\nsetps: 3\n")
    with pytest.raises(ValueError) as e:
        load_config(f, Run)
    msg = str(e.value)
    assert f.as_posix() in msg and "unknown config keys ['setps']" in msg
    assert "Run knows ['clip_x0', 'clips', 'config_file', 'ema', 'horizons', 'lr'" in msg


@pytest.mark.parametrize(
    "text, error",
    [
        ("steps: 2.5\n", "steps must be int, got 2.5"),
        ("steps: many\n", "steps must be int, got 'many'"),
        ("steps: true\n", "steps must be int, got True"),
        ("steps: null\n", "steps must be int, got None"),
        ("lr: fast\n", "lr must be float, got 'fast'"),
        ("name: 3\n", "name must be str, got 3"),
        ("ema: 1\n", "ema must be bool, got 1"),
        ("horizons: [1, x]\n", "horizons\\[1\\] must be int, got 'x'"),
        ("horizons: 3\n", "horizons must be list\\[int\\], got 3"),
        ("clip_x0: big\n", "clip_x0 must be float \\| None, got 'big'"),
        ("- 1\n- 2\n", "must hold a mapping of Run fields, got list"),
    ],
)
def test_wrong_types_are_errors_that_name_the_field_and_the_file(tmp_path, text, error):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(ValueError, match=error) as e:
        load_config(f, Run)
    assert f.as_posix() in str(e.value)


def test_whole_numbers_and_numeric_strings_convert(tmp_path):
    f = tmp_path / "ok.yaml"
    f.write_text("steps: 1e3\nlr: 3\nclip_x0: '2'\n")  # YAML: "1e3" is a string, 3 an int
    run = load_config(f, Run)
    assert run.steps == 1000 and isinstance(run.steps, int)
    assert run.lr == 3.0 and isinstance(run.lr, float) and run.clip_x0 == 2.0
    with pytest.raises(ValueError, match=r"\.yaml, \.yml or \.toml"):
        load_config(tmp_path / "run.json", Run)


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_a_float_written_as_text_comes_back_exactly(x):
    assert from_dict(Run, {"lr": repr(x)}).lr == x
    assert from_dict(Run, {"lr": f"{x:e}"}).lr == pytest.approx(x, rel=1e-5)


def test_with_changes_copies_checks_and_converts():
    base = Run()
    new = with_changes(base, {"lr": "2e-4", "steps": 7}, where="--set")
    assert (new.lr, new.steps, base.lr, base.steps) == (2e-4, 7, 1e-3, 10)
    with pytest.raises(ValueError, match=r"--set: unknown config keys \['stpes'\]"):
        with_changes(base, {"stpes": 7}, where="--set")
    with pytest.raises(TypeError, match="must be a dataclass"):
        from_dict(dict, {})


def test_every_shipped_config_loads_into_its_dataclass():
    from minimdm.camdm.classifier import ClassifierConfig
    from minimdm.camdm.train_config import CAMDMTrainConfig
    from minimdm.rl.train import RLConfig

    for f in sorted((ROOT / "configs").glob("*.yaml")):
        cls = AAMDMTrainConfig if f.name.startswith("aamdm") else TrainConfig
        cls = RLConfig if f.name.startswith("rl_") else cls
        cls = CAMDMTrainConfig if f.name.startswith("camdm") else cls
        cls = ClassifierConfig if f.name == "camdm_classifier.yaml" else cls
        cfg = load_config(f, cls)
        for name, value in vars(cfg).items():  # every float field holds a float
            if isinstance(getattr(cls, name, None), float) and value is not None:
                assert isinstance(value, float) and math.isfinite(value), (f.name, name)


def test_cli_set_overrides_go_through_the_loader(capsys, tmp_path):
    code = cli.main(["train", BOOK, "--set", "widht=3", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert (
        code == 2 and "--set: unknown config keys ['widht']" in err and "TrainConfig knows" in err
    )
    code = cli.main(["train", BOOK, "--set", "depth=deep", "--out", str(tmp_path)])
    assert code == 2 and "depth must be int, got 'deep'" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing was trained or written


def test_rl_command_rejects_a_bad_config_before_training(capsys, tmp_path):
    code = cli.main(["rl", str(ROOT / "configs" / "rl_target.yaml"), "--set", "tsk=path",
                     "--out", str(tmp_path)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "--set: unknown config keys ['tsk']" in err and "RLConfig knows" in err
    code = cli.main(["rl", str(ROOT / "configs" / "rl_target.yaml"), "--set", "task=dance",
                     "--out", str(tmp_path)])  # fmt: skip
    assert (
        code == 2
        and "task must be one of ['joystick', 'path', 'target']" in capsys.readouterr().err
    )
    assert not any(tmp_path.iterdir())
