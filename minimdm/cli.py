"""The ``minimdm`` command line: train, sample and evaluate.

::

    minimdm train configs/amdm.yaml                      # -> runs/amdm/
    minimdm train configs/amdm.yaml --ship               # -> checkpoints/amdm/ (the book's)
    minimdm sample --checkpoint checkpoints/amdm --frames 300 --out walk.gif
    minimdm eval --checkpoint checkpoints/amdm --json
    minimdm data list                                    # known corpora, licences, present?
    minimdm data download lafan1                         # -> $MINIMDM_DATA/lafan1/
    minimdm camdm train configs/camdm.yaml               # -> runs/camdm/ (chapter 9)
    minimdm camdm classifier configs/camdm_classifier.yaml  # -> runs/camdm_classifier/
    minimdm export --onnx checkpoints/amdm --out amdm.onnx  # one frame as one ONNX graph
    minimdm export --onnx checkpoints/camdm                 # a CAMDM planning call, the same
    python -m minimdm.aamdm train configs/aamdm.yaml     # -> runs/aamdm/ (chapter 8)

The trainers (``train``, ``rl``, ``camdm train``, ``camdm classifier`` and ``python -m
minimdm.aamdm train``) write to ``runs/<config stem>/`` under the current folder unless
``--out`` says otherwise. A folder inside the shipped ``checkpoints/`` (however it is spelled)
is refused unless ``--ship`` says so in so many words; ``--ship`` alone writes the shipped
checkpoint ``checkpoints/<config stem>/`` and is recorded in its ``command``. A run holds
``run.lock`` in its folder (:class:`minimdm.files.RunLock`): a second run into the same folder
is refused, naming the first. ``train`` resumes from the output folder's training state when
there is one, so an interrupted run continues where it stopped.

``sample`` writes ``.npz`` (a ``positions`` array ``(F, J, 3)`` in metres, z-up, plus the
features), ``.bvh`` (opens in Blender) or ``.gif`` / ``.mp4``, each atomically. ``eval``
prints the Table 1 metrics of A-MDM §7.3. ``export --onnx`` writes a frame of the model, every
denoising step, as one ONNX graph with its metadata (:mod:`minimdm.fast`; for CAMDM a whole
planning call: 8 steps with classifier-free guidance).
``data download`` fetches a corpus (resuming an interrupted download), checks it and unpacks it
into the data folder (:func:`minimdm.motion.corpora.data_home`).

Every command has one error path (:func:`run`): a user error (bad input, a file that cannot be
read or written, a full disk, a folder in use) is one line ``minimdm CMD: error: ...`` naming
the option, config key or file, with exit status 2; ``--debug`` shows its traceback instead.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from minimdm.files import WriteError
from minimdm.validate import (
    InputError,
    InputTypeError,
    check_device,
    check_output_dir,
    check_output_file,
)

__all__ = ["main", "aamdm_main", "build_parser", "build_aamdm_parser", "run", "USER_ERRORS"]

CHECKPOINTS = Path(__file__).resolve().parent.parent / "checkpoints"
"""Where shipped checkpoints live in a source checkout (``minimdm.pretrained`` looks here)."""
RUNS = Path("runs")
"""Where the trainers write by default: ``runs/<config stem>/`` under the current folder."""
MAX_SAMPLED_FRAMES = 1_000_000
"""The most frames ``minimdm sample`` makes in all (``--frames`` times ``--samples``): about 9
hours of motion at 30 fps, a file of about 1.3 GB for a 21-joint skeleton."""


def _overrides(pairs: list[str]) -> dict:
    """``["T=5", "width=256"]`` -> ``{"T": 5, "width": 256}`` (values parsed as YAML)."""
    import yaml

    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects KEY=VALUE, got {pair!r}")
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError as e:
            problem = getattr(e, "problem", None) or str(e).splitlines()[0]
            raise ValueError(f"--set {pair!r}: the value is not valid YAML: {problem}") from None
    return out


def _shipped_roots() -> list[Path]:
    """The shipped checkpoint folders: the checkout's ``checkpoints/`` and
    ``minimdm.CHECKPOINT_DIR`` (``$MINIMDM_CHECKPOINTS``), symlinks resolved."""
    from minimdm import CHECKPOINT_DIR

    return list(dict.fromkeys(Path(os.path.realpath(p)) for p in (CHECKPOINTS, CHECKPOINT_DIR)))


def _shipped_root_of(folder: Path) -> Path | None:
    """The shipped checkpoint folder that holds ``folder`` (however it is spelled), or None."""
    real = Path(os.path.realpath(folder))
    return next((r for r in _shipped_roots() if real == r or r in real.parents), None)


def _train_out(args: argparse.Namespace) -> Path:
    """The output folder of a training command, checked before any work: ``--out``, else
    ``runs/<config stem>`` (with ``--ship``: the shipped ``checkpoints/<config stem>``). A
    folder inside the shipped checkpoints is refused without ``--ship``."""
    from minimdm import CHECKPOINT_DIR

    stem = Path(args.config).stem
    if args.out is not None:
        out = check_output_dir("--out", args.out)  # '' is refused here
    else:
        out = CHECKPOINT_DIR / stem if args.ship else RUNS / stem
    root = _shipped_root_of(out)
    if root is not None and not args.ship:
        raise InputError(
            f"--out {out} lies in {root}, the shipped checkpoints the book loads; pass --ship to "
            f"replace a shipped checkpoint deliberately, or write elsewhere (default: "
            f"{RUNS / stem})"
        )
    return check_output_dir("--out", out)


def _recorded_command(prog: str, verb: str, args: argparse.Namespace, threads: int) -> str:
    """The command line a checkpoint records: ``PROG VERB CONFIG [--set ...] [--out ...]
    [--ship] [--threads N]``; a shipped folder is spelled from the project root."""
    import shlex

    command = [prog, verb, Path(args.config).as_posix()]
    overrides = sorted(_overrides(getattr(args, "set", None) or []).items())
    command += [f"--set {k}={v}" for k, v in overrides]
    if args.out is not None:
        out = Path(args.out)
        root = _shipped_root_of(out)
        if root is not None:  # checkpoints/amdm_steps/T5, wherever the checkout lies
            out = Path(root.name) / Path(os.path.realpath(out)).relative_to(root)
        command.append(f"--out {shlex.quote(out.as_posix())}")
    if args.ship:
        command.append("--ship")
    if args.threads != threads:
        command.append(f"--threads {args.threads}")
    return " ".join(command)


def _cmd_train(args: argparse.Namespace) -> int:
    from minimdm.amdm.train import load_config, train_amdm
    from minimdm.config import with_changes

    check_device("--device", args.device)
    out = _train_out(args)  # before the corpus is loaded
    config = load_config(args.config)
    changes = _overrides(args.set or [])
    if args.steps is not None:
        changes["total_steps"] = args.steps
    if args.device is not None:
        changes["device"] = args.device
    config = with_changes(config, changes, where="--set")
    check_device("device (of the config)", config.device)
    result = train_amdm(
        config,
        out,
        resume=not args.restart,
        progress=not args.quiet,
        num_threads=args.threads,
        metadata={"command": _recorded_command("minimdm", "train", args, 1)},
    )
    summary = {
        "checkpoint": str(result.checkpoint.paths.weights),
        "steps": result.steps,
        "seconds": round(result.seconds, 1),
        "train_seconds": result.checkpoint.metadata.get("train_seconds"),  # all resumed runs
        "steps_per_second": round(result.steps_per_second, 2),
        "eval_loss": next(
            (r["eval_loss"] for r in reversed(result.history) if "eval_loss" in r), None
        ),
    }
    print(json.dumps(summary))
    return 0


def _cmd_rl(args: argparse.Namespace) -> int:
    from minimdm.config import with_changes
    from minimdm.rl.train import load_config, train_policy

    out = _train_out(args)  # before the base model is loaded
    config = with_changes(load_config(args.config), _overrides(args.set or []), where="--set")
    result = train_policy(
        config,
        out,
        progress=not args.quiet,
        num_threads=args.threads,
        metadata={"command": _recorded_command("minimdm", "rl", args, 2)},
    )
    summary = {
        "checkpoint": str(result.checkpoint.paths.weights),
        "env_steps": result.env_steps,
        "seconds": round(result.seconds, 1),
        "final_reward_mean": result.checkpoint.metadata.get("final_reward_mean"),
    }
    print(json.dumps(summary))
    return 0


def _cmd_camdm_train(args: argparse.Namespace) -> int:
    from minimdm.camdm.train import load_train_config, train_camdm
    from minimdm.config import with_changes

    out = _train_out(args)  # before the corpus is loaded
    changes = _overrides(args.set or [])
    if args.steps is not None:
        changes["total_steps"] = args.steps
    config = with_changes(load_train_config(args.config), changes, where="--set")
    check_device("device (of the config)", config.device)
    ckpt = train_camdm(
        config,
        out,
        resume=not args.restart,
        progress=not args.quiet,
        num_threads=args.threads,
        metadata={"command": _recorded_command("minimdm", "camdm train", args, 1)},
    )
    summary = {
        "checkpoint": str(ckpt.paths.weights),
        "steps": ckpt.step,
        "train_seconds": ckpt.metadata.get("train_seconds"),
    }
    print(json.dumps(summary))
    return 0


def _cmd_camdm_classifier(args: argparse.Namespace) -> int:
    from minimdm.camdm.classifier import load_classifier_config, train_classifier
    from minimdm.config import with_changes

    out = _train_out(args)
    config = with_changes(
        load_classifier_config(args.config), _overrides(args.set or []), where="--set"
    )
    ckpt = train_classifier(
        config,
        out,
        progress=not args.quiet,
        num_threads=args.threads,
        metadata={"command": _recorded_command("minimdm", "camdm classifier", args, 1)},
    )
    summary = {
        "checkpoint": str(ckpt.paths.weights),
        "heldout_accuracy": ckpt.metadata.get("heldout_accuracy"),
        "train_seconds": ckpt.metadata.get("train_seconds"),
    }
    print(json.dumps(summary))
    return 0


def _parse_start(text: str) -> tuple[str, int]:
    """``"clip:frame"`` -> (clip, frame); ``"clip"`` -> (clip, 0), taken as frame 1."""
    name, _, frame = text.rpartition(":")
    if not name or not frame.lstrip("+-").isdigit():
        return text, 0
    if int(frame) < 1:
        raise InputError(
            f"--start must be CLIP or CLIP:FRAME with FRAME >= 1 (frame 0 has no velocity), "
            f"got {text!r}"
        )
    return name, int(frame)


SAMPLED_KINDS = ("amdm", "mse", "mvae")
"""The checkpoint kinds ``minimdm sample`` and ``minimdm eval`` roll out."""


def _check_kind(ckpt, command: str) -> None:
    """:class:`InputError` unless the checkpoint holds a model this command can roll out."""
    if ckpt.kind in SAMPLED_KINDS:
        return
    hint = {
        "aamdm_motion": " (AAMDM models sample with minimdm.aamdm.eval.rollout_aamdm)",
        "policy": " (a steering policy runs on its base model with minimdm.rl.rollout.steer)",
        "camdm": " (CAMDM runs with minimdm.camdm.controller.CAMDMController)",
        "style_classifier": " (a style classifier: minimdm.camdm.classifier.predict_styles)",
    }.get(ckpt.kind, "")
    raise InputError(
        f"--checkpoint must hold an A-MDM, MVAE or MSE model (kinds {', '.join(SAMPLED_KINDS)}) "
        f"for minimdm {command}, but {ckpt.paths.weights} holds kind {ckpt.kind!r}{hint}"
    )


def _cmd_sample(args: argparse.Namespace) -> int:
    from minimdm import viz
    from minimdm.amdm import evaluation
    from minimdm.amdm.sampling import history_of, rollout
    from minimdm.checkpoint import load_checkpoint
    from minimdm.files import atomic_output
    from minimdm.motion import bvh, features

    # Everything the user gave is checked before the first frame is sampled: a bad --out must
    # not throw away minutes of sampling.
    out = check_output_file("--out", args.out, (".npz", ".bvh", ".gif", ".mp4"))
    if args.frames * args.samples > MAX_SAMPLED_FRAMES:  # before anything is allocated
        raise InputError(
            f"--frames times --samples must be at most {MAX_SAMPLED_FRAMES} frames in all, got "
            f"{args.frames} x {args.samples} = {args.frames * args.samples}"
        )
    device = check_device("--device", args.device)
    start = _parse_start(args.start) if args.start is not None else None
    ckpt = load_checkpoint(args.checkpoint, device=device)
    _check_kind(ckpt, "sample")
    if start is None:
        split = "test" if ckpt.config.get("split") == "train" else "train"
        start = evaluation.checkpoint_clips(ckpt, split=split)[0].name, 0
    name, frame = start
    state = evaluation.initial_state(ckpt, name, frame)
    g = torch.Generator(device=device).manual_seed(args.seed)
    roll = rollout(
        ckpt,
        state.condition(history_of(ckpt.model)),  # x_0, or the frames that end with it
        args.frames,
        n_samples=args.samples,
        steps=args.steps,
        generator=g,
        start_pose=state.start_pose,
        device=device,
        progress=not args.quiet,
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    pos = roll.positions[0].numpy()  # (K, F, J, 3)
    feats = roll.features[0].numpy()  # (K, F, D)
    skeleton = evaluation.checkpoint_skeleton(ckpt)
    if out.suffix.lower() == ".npz":
        squeeze = args.samples == 1
        with atomic_output(out) as tmp:
            np.savez_compressed(
                tmp,
                positions=pos[0] if squeeze else pos,
                features=feats[0] if squeeze else feats,
                parents=np.asarray(skeleton.parents),
                joint_names=np.asarray(skeleton.names),
                fps=np.asarray(ckpt.fps),
            )
    elif out.suffix.lower() == ".bvh":
        for k in range(args.samples):
            path = out if args.samples == 1 else out.with_name(f"{out.stem}_{k}{out.suffix}")
            sp = features.StartPose(state.start_pose.xy, state.start_pose.heading)
            clip = features.decode_clip(torch.as_tensor(feats[k]), sp, skeleton, fps=ckpt.fps)
            bvh.save_bvh(path, clip)
    else:
        labels = [f"sample {k}" for k in range(args.samples)]
        viz.animate(list(pos), skeleton, labels=labels, colors=viz.GENERATED, out=out)
    print(json.dumps({"out": str(out), "frames": args.frames, "samples": args.samples}))
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from minimdm.amdm import evaluation
    from minimdm.checkpoint import load_checkpoint

    device = check_device("--device", args.device)
    ckpt = load_checkpoint(args.checkpoint, device=device)
    _check_kind(ckpt, "eval")
    protocol = evaluation.Protocol(
        n_states=args.states, n_samples=args.samples, seeds=tuple(range(args.seeds))
    )
    have = evaluation.available_states(ckpt, protocol)
    if args.states > have:
        raise InputError(
            f"--states must be at most {have} (the frames of {ckpt.paths.weights}'s evaluation "
            f"takes with {protocol.ade_frames} frames after them), got {args.states}"
        )
    table = evaluation.table1(
        {Path(args.checkpoint).name: ckpt}, protocol, steps=args.steps, device=device
    )
    row = next(iter(table.values()))
    if args.json:
        cells = {k: {"mean": round(m, 4), "std": round(sd, 4)} for k, (m, sd) in row.items()}
        info = {"checkpoint": str(args.checkpoint), "protocol": protocol.to_dict()}
        print(json.dumps({**info, "steps": args.steps, "unit": "cm", **cells}))
    else:
        print(evaluation.format_table(table))
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from minimdm.fast import export_onnx, frame_graph
    from minimdm.fast.graphs import load

    src = Path(args.onnx)
    default = Path(f"{(src.parent if src.suffix == '.safetensors' else src).name}.onnx")
    out = check_output_file("--out", args.out or default, (".onnx",))  # before any work
    ckpt = load(args.onnx)
    options = {}
    if args.guide is not None:
        if ckpt.kind != "camdm":
            raise InputError(
                f"--guide: only a CAMDM checkpoint (kind camdm) guides, got kind {ckpt.kind!r} "
                f"({args.onnx})"
            )
        options["guide"] = args.guide
    graph = frame_graph(ckpt, steps=args.steps, eta=args.eta, **options)
    data = export_onnx(graph, out, weights=args.weights)
    output = graph.output()
    report = {
        "out": str(out),
        "kind": graph.kind,
        "bytes": len(data),
        "noise_dim": graph.noise_dim,
        "inputs": {p.name: list(p.shape) for p in graph.inputs()},
        "output": {output.name: list(output.shape)},
    }
    print(json.dumps(report))
    return 0


def _cmd_data_list(args: argparse.Namespace) -> int:
    from minimdm.motion.corpora import data_home, list_corpora

    rows = list_corpora()
    widths = {k: max(len(k), *(len(r[k]) for r in rows)) for k in rows[0]}
    for r in [{k: k for k in widths}, *rows]:  # a header row, then one row per corpus
        print("  ".join(r[k].ljust(w) for k, w in widths.items()).rstrip())
    print(f"data folder: {data_home()}")
    return 0


def _cmd_data_download(args: argparse.Namespace) -> int:
    from minimdm.motion.corpora import download_corpus

    folder = download_corpus(args.name, force=args.force, url=args.url, progress=not args.quiet)
    print(json.dumps({"corpus": args.name, "folder": str(folder)}))
    return 0


def _int_arg(low: int, high: int | None = None):
    """An argparse type: an integer >= ``low`` (and <= ``high``); argparse then reports
    ``minimdm CMD: error: argument --NAME: ...``."""
    words = f"an integer >= {low}" if high is None else f"an integer in [{low}, {high}]"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {words}, got {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {words}, got {value}")
        return value

    parse.__name__ = words.removeprefix("an ")
    return parse


def _add_out(p: argparse.ArgumentParser, what: str = "checkpoint folder") -> None:
    """``--out`` and ``--ship`` of a training command."""
    p.add_argument("--out", help=f"{what} (default: runs/<config stem>)")
    p.add_argument(
        "--ship",
        action="store_true",
        help="replace the shipped checkpoint: write into checkpoints/ (default "
        "checkpoints/<config stem>); without it a folder in checkpoints/ is refused",
    )


_AddParser = Callable[..., argparse.ArgumentParser]
"""``add(name, help=...)``: a new subcommand's parser, which takes ``--debug``."""


def _add_train_parser(add: _AddParser) -> None:
    t = add("train", help="train a model from a YAML config (resumes if it can)")
    t.add_argument("config", help="a YAML file of configs/, e.g. configs/amdm.yaml")
    _add_out(t)
    t.add_argument("--steps", type=_int_arg(1), help="override total_steps")
    t.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)"
    )
    t.add_argument("--device", help="override the config's device (cpu, cuda)")
    t.add_argument("--threads", type=_int_arg(1), default=1, help="torch CPU threads (default 1)")
    t.add_argument("--restart", action="store_true", help="ignore an existing training state")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(fn=_cmd_train)


def _add_rl_parser(add: _AddParser) -> None:
    r = add("rl", help="train a steering policy with PPO (chapter 7)")
    r.add_argument("config", help="a YAML file of configs/, e.g. configs/rl_target.yaml")
    _add_out(r, "policy folder")
    r.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)"
    )
    r.add_argument("--threads", type=_int_arg(1), default=2, help="torch CPU threads (default 2)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.set_defaults(fn=_cmd_rl)


def _add_camdm_parser(add: _AddParser, common: argparse.ArgumentParser) -> None:
    """``camdm train`` and ``camdm classifier``."""
    c = add("camdm", help="train CAMDM or its style classifier (chapter 9)")
    csub = c.add_subparsers(dest="camdm_command", required=True)
    cadd = functools.partial(csub.add_parser, parents=[common])
    for verb, fn, what in (
        ("train", _cmd_camdm_train, "the CAMDM denoiser, e.g. configs/camdm.yaml"),
        (
            "classifier",
            _cmd_camdm_classifier,
            "the style classifier, configs/camdm_classifier.yaml",
        ),
    ):
        ct = cadd(verb, help=f"train {what.split(',')[0]}")
        ct.add_argument("config", help=f"a YAML file of configs/: {what}")
        _add_out(ct)
        ct.add_argument(
            "--set", action="append", metavar="KEY=VALUE", help="override a config field"
        )
        ct.add_argument("--threads", type=_int_arg(1), default=1, help="torch CPU threads")
        ct.add_argument("--quiet", action="store_true", help="no progress bar")
        if verb == "train":
            ct.add_argument("--steps", type=_int_arg(1), help="override total_steps")
            ct.add_argument("--restart", action="store_true", help="ignore a training state")
        ct.set_defaults(fn=fn)


def _add_sample_parser(add: _AddParser) -> None:
    s = add("sample", help="roll a trained model out and save the motion")
    s.add_argument("--checkpoint", required=True, help="checkpoint folder or file")
    frames = _int_arg(1, MAX_SAMPLED_FRAMES)
    s.add_argument("--frames", type=frames, required=True, help="frames to generate")
    s.add_argument("--out", required=True, help="output .npz, .bvh, .gif or .mp4")
    samples = _int_arg(1, 10_000)
    s.add_argument("--samples", type=samples, default=1, help="futures from the start pose")
    s.add_argument("--steps", type=_int_arg(1), default=None, help="denoising steps (default: T)")
    s.add_argument(
        "--start",
        default=None,
        help="start clip[:frame], e.g. dataset-1_run_normal_001:10 (default: the first held-out "
        "take, or the first training clip)",
    )
    s.add_argument("--seed", type=_int_arg(0, 2**63 - 1), default=0)
    s.add_argument("--device", default="cpu")
    s.add_argument("--threads", type=_int_arg(1), default=1, help="torch CPU threads (default 1)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(fn=_cmd_sample)


def _add_eval_parser(add: _AddParser) -> None:
    e = add("eval", help="the Table 1 metrics of A-MDM §7.3")
    e.add_argument("--checkpoint", required=True, help="checkpoint folder or file")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.add_argument("--states", type=_int_arg(1), default=10, help="fixed initial states")
    samples, seeds = _int_arg(2, 10_000), _int_arg(1, 1000)
    e.add_argument("--samples", type=samples, default=50, help="samples per initial state")
    e.add_argument("--seeds", type=seeds, default=3, help="repeated seeds (mean ± std)")
    e.add_argument("--steps", type=_int_arg(1), default=None, help="denoising steps (default: T)")
    e.add_argument("--device", default="cpu")
    e.add_argument("--threads", type=_int_arg(1), default=2, help="torch CPU threads (default 2)")
    e.set_defaults(fn=_cmd_eval)


def _add_export_parser(add: _AddParser) -> None:
    x = add("export", help="write a checkpoint's frame as one ONNX graph, for game engines")
    x.add_argument(
        "--onnx",
        required=True,
        metavar="CHECKPOINT",
        help="checkpoint folder, file or shipped name (kinds amdm, aamdm_motion, policy, camdm)",
    )
    x.add_argument("--out", help="the .onnx file (default: <checkpoint name>.onnx here)")
    x.add_argument("--steps", type=_int_arg(1), default=None, help="A-MDM: DDIM steps")
    x.add_argument("--eta", type=float, default=1.0, help="A-MDM: DDIM stochasticity")
    guide_help = (
        "CAMDM: what CFG drops (default past: CFG-PM; style: CFG-S; each: an input on_style "
        "says, per sample; none: no guidance, the conditional model alone, half the arithmetic, "
        "for plans at gamma 1)"
    )
    guides = ("past", "style", "each", "none")
    x.add_argument("--guide", choices=guides, default=None, help=guide_help)
    x.add_argument(
        "--weights",
        choices=("fp32", "int8"),
        default="fp32",
        help="int8: 8-bit block weights, a quarter of the bytes, approximate (default fp32)",
    )
    x.set_defaults(fn=_cmd_export)


def _add_data_parser(add: _AddParser, common: argparse.ArgumentParser) -> None:
    """``data list`` and ``data download``."""
    d = add("data", help="list and download motion corpora")
    dsub = d.add_subparsers(dest="data_command", required=True)
    add = functools.partial(dsub.add_parser, parents=[common])
    dl = add("list", help="known corpora: licence, description, present or not")
    dl.set_defaults(fn=_cmd_data_list)
    dd = add("download", help="download and unpack a corpus (resumes if it can)")
    dd.add_argument("name", help="a corpus name, e.g. lafan1 (see `minimdm data list`)")
    dd.add_argument("--force", action="store_true", help="download and unpack again")
    dd.add_argument("--url", help="fetch from this address instead (a mirror or file://)")
    dd.add_argument("--quiet", action="store_true", help="no progress bar")
    dd.set_defaults(fn=_cmd_data_download)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``minimdm`` command."""
    p = argparse.ArgumentParser(prog="minimdm", description=__doc__.split("\n\n")[0])
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--debug", action="store_true", help="show the traceback of an error, not one line"
    )
    sub = p.add_subparsers(dest="command", required=True)
    add = functools.partial(sub.add_parser, parents=[common])  # every command takes --debug
    _add_train_parser(add)
    _add_rl_parser(add)
    _add_camdm_parser(add, common)
    _add_sample_parser(add)
    _add_eval_parser(add)
    _add_export_parser(add)
    _add_data_parser(add, common)
    return p


def _cmd_aamdm_train(args: argparse.Namespace) -> int:
    from minimdm.aamdm.motion_train import load_train_config, train_aamdm_motion
    from minimdm.config import with_changes
    from minimdm.utils import num_threads

    out = _train_out(args)  # before the corpus is loaded
    config = with_changes(load_train_config(args.config), _overrides(args.set or []), where="--set")
    command = _recorded_command("python -m minimdm.aamdm", "train", args, 1)
    with num_threads(args.threads):
        _, report = train_aamdm_motion(config, out, progress=not args.quiet, command=command)
    print(json.dumps({"checkpoint": str(out), **report}))
    return 0


def build_aamdm_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m minimdm.aamdm`` (chapter 8's motion AAMDM)."""
    p = argparse.ArgumentParser(prog="python -m minimdm.aamdm", description="Train a motion AAMDM.")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--debug", action="store_true", help="show the traceback of an error, not one line"
    )
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", parents=[common], help="train a motion AAMDM from a YAML config")
    t.add_argument("config", help="a YAML file of configs/, e.g. configs/aamdm.yaml")
    _add_out(t)
    t.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)"
    )
    t.add_argument("--threads", type=_int_arg(1), default=1, help="torch CPU threads (default 1)")
    t.add_argument("--quiet", action="store_true", help="no progress lines")
    t.set_defaults(fn=_cmd_aamdm_train)
    return p


USER_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,  # InputError, BVHError, CheckpointError, CheckpointMismatchError, config errors
    InputTypeError,
    FileNotFoundError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
    WriteError,  # a full disk, a read-only folder: the file is named, nothing is left behind
)
"""What the commands report as one line ``PROG CMD: error: ...`` (exit code 2): bad input,
unreadable or unwritable files, a folder in use by another run, and every error the library
raises for them. Anything else is a bug and keeps its traceback; ``--debug`` shows the
traceback of these too."""


def run(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse ``argv`` and run its command: the one error path of every command (module
    docstring). The parser's commands set ``fn`` and take ``--debug``; a command with
    ``--threads`` runs on that many torch threads (the library leaves threads to its callers)."""
    from minimdm.amdm.sampling import NonFiniteFrameError
    from minimdm.motion.download import DownloadError
    from minimdm.utils import num_threads

    args = parser.parse_args(argv)
    try:
        with num_threads(getattr(args, "threads", None)):
            return args.fn(args)
    except (*USER_ERRORS, DownloadError, NonFiniteFrameError) as e:
        if args.debug:
            raise
        sub = getattr(args, "data_command", None) or getattr(args, "camdm_command", None)
        where = " ".join(filter(None, [parser.prog, args.command, sub]))
        message = "; ".join(line.strip() for line in str(e).splitlines() if line.strip())
        print(f"{where}: error: {message}", file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``minimdm`` console script."""
    return run(build_parser(), argv)


def aamdm_main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m minimdm.aamdm``."""
    return run(build_aamdm_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
