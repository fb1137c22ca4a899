"""Bad input never passes silently and never costs work: one table over the API, the CLI, BVH
files, configs and checkpoints.

Each row is an input and the words its message must contain: what was wrong (the argument, the
file and line) and what was expected. A new entry point joins the table with its bad inputs.
Every row runs in this process on a tiny untrained model of a 4-joint skeleton, so the whole
table takes seconds.
"""

from __future__ import annotations

import errno
import json
import os
import pickle
import re
import socket
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from safetensors.torch import save as st_save

from minimdm.amdm.evaluation import initial_state
from minimdm.amdm.models import DenoiserConfig, MLPDenoiser
from minimdm.amdm.sampling import autoregress, rollout
from minimdm.amdm.train import TrainConfig, read_log, train_amdm
from minimdm.checkpoint import (
    CheckpointError,
    CheckpointMismatchError,
    load_checkpoint,
    load_train_state,
    save_checkpoint,
)
from minimdm.cli import main
from minimdm.config import load_config
from minimdm.control import Sampler, beam_search, inbetween, inpaint, lerp_inbetween
from minimdm.fast import FastFrame, export_onnx, frame_graph
from minimdm.files import LOCK_NAME, LockedError, RunLock, WriteError, atomic_write
from minimdm.motion.bvh import BVHError, load_bvh, save_bvh
from minimdm.motion.data import Clip, resample_clip
from minimdm.motion.download import DownloadError
from minimdm.motion.features import FeatureLayout, Normalizer, StartPose, encode, start_pose_of
from minimdm.motion.skeleton import Skeleton, axis_angle_to_quat
from minimdm.rl import load_steering
from minimdm.rl.train import RLConfig
from minimdm.validate import InputError, InputTypeError, MismatchError

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

J = 4
D = 3 + 12 * J  # 51
T = 4
NO_CUDA = not torch.cuda.is_available()
NAN = float("nan")


def make_clip(names: list[str], n_frames: int = 8, fps: float = 30.0, seed: int = 0) -> Clip:
    """A small standing body (1.5 m tall) that sways: hips, a spine chain and one leg."""
    J_ = len(names)
    parents = [-1] + [0] * min(1, J_ - 1) + list(range(1, J_ - 2)) + ([0] if J_ > 2 else [])
    parents = parents[:J_]
    offsets = np.zeros((J_, 3))
    offsets[0] = [0.0, 0.0, 1.0]
    offsets[1:] = [0.0, 0.0, 0.3]
    offsets[-1] = [0.0, 0.1, -0.9]  # the leg
    sk = Skeleton(names, parents, offsets, foot_joints=[names[-1]])
    g = torch.Generator().manual_seed(seed)
    aa = 0.1 * torch.randn(n_frames, J_, 3, generator=g, dtype=torch.float64)
    root = np.zeros((n_frames, 3))
    root[:, 0] = np.arange(n_frames) * 0.03
    root[:, 2] = 1.0
    return Clip("synthetic", fps, sk, root, axis_angle_to_quat(aa).numpy())


MODEL_JOINTS = ["Hips", "Spine", "Head", "Leg"]
OTHER_JOINTS = ["pelvis", "torso", "skull", "thigh"]  # same tree, another skeleton


@pytest.fixture(scope="module")
def ctx(tmp_path_factory) -> SimpleNamespace:
    """A tiny untrained A-MDM checkpoint whose corpus is a folder of one BVH clip, and the
    files the rows corrupt."""
    root = tmp_path_factory.mktemp("bad_input")
    corpus = root / "corpus"
    corpus.mkdir()
    save_bvh(corpus / "sway.bvh", make_clip(MODEL_JOINTS, n_frames=12))
    clip = load_bvh(corpus / "sway.bvh")
    clip.name = "sway"
    sk = clip.skeleton
    feats = encode(clip)  # (11, D)
    norm = Normalizer.fit(feats)
    torch.manual_seed(0)
    model = MLPDenoiser(DenoiserConfig(D, D, width=16, depth=2, time_dim=8))
    meta = {
        "config": {"corpus": str(corpus), "fps": 30.0, "split": None, "loop_frames": None},
        "data": {"clips": ["sway"]},
        "feature_layout": FeatureLayout.for_skeleton(sk, 30.0),
        "skeleton": sk,
        "normalizer": norm,
        "diffusion": {"schedule": "cosine", "T": T, "predicts": "eps", "clip_x0": None},
    }
    state = {"step": 1, "model": model.state_dict()}
    (root / "ckpt").mkdir()
    save_checkpoint(root / "ckpt", model, meta, optimizer_state=state)
    ck = load_checkpoint(root / "ckpt")
    other = make_clip(OTHER_JOINTS)
    (root / "a_file").write_text("not a folder\n")
    (root / "out_dir").mkdir()
    (root / "folder.npz").mkdir()
    return SimpleNamespace(
        root=root,
        corpus=corpus,
        ck=ck,
        ckdir=str(root / "ckpt"),
        clip=clip,
        x0=feats[3],
        other=other,
        other_x0=encode(other)[-1],
        three=make_clip(["a", "b", "c"]),
        at60=make_clip(MODEL_JOINTS, fps=60.0),
        weights=(root / "ckpt" / "model.safetensors").read_bytes(),
        cache={},
    )


# --------------------------------------------------------------------------------------------
# Rows


@dataclass
class Row:
    """One bad input: ``run(ctx)`` must raise ``error`` (or, for the CLI, exit with 2), and the
    message must contain every one of ``words``."""

    id: str
    run: Callable[[SimpleNamespace], Any]
    error: type[BaseException] | str
    words: tuple[str, ...]
    skip: str | None = None


ROWS: list[Row] = []


def row(id: str, error, *words: str, skip: str | None = None):
    def add(run):
        ROWS.append(Row(id, run, error, words, skip))
        return run

    return add


def api(id: str, error, words: tuple[str, ...], run, skip: str | None = None) -> None:
    ROWS.append(Row(id, run, error, words, skip))


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# --- rollout: scalars, devices, randomness ---------------------------------------------------
R = rollout
api("rollout/n_frames=True", InputTypeError, ("n_frames", "integer", "True"),
    lambda c: R(c.ck, c.x0, True))  # fmt: skip
api("rollout/n_frames=0", InputError, ("n_frames", ">= 1", "0"), lambda c: R(c.ck, c.x0, 0))
api("rollout/n_frames=2.0", InputTypeError, ("n_frames", "2.0"), lambda c: R(c.ck, c.x0, 2.0))
api("rollout/n_frames='3'", InputTypeError, ("n_frames", "'3'"), lambda c: R(c.ck, c.x0, "3"))
api("rollout/n_samples=0", InputError, ("n_samples", ">= 1"), lambda c: R(c.ck, c.x0, 2, 0))
api("rollout/n_samples=-1", InputError, ("n_samples", "-1"), lambda c: R(c.ck, c.x0, 2, -1))
api("rollout/steps=2.5", InputTypeError, ("steps", "integer", "2.5"),
    lambda c: R(c.ck, c.x0, 2, steps=2.5))  # fmt: skip
api("rollout/steps=0", InputError, ("steps", ">= 1"), lambda c: R(c.ck, c.x0, 2, steps=0))
api("rollout/steps>T", InputError, ("steps", f"T={T}", "99"),
    lambda c: R(c.ck, c.x0, 2, steps=99))  # fmt: skip
api("rollout/generator=42", InputTypeError, ("generator", "torch.Generator", "manual_seed(42)"),
    lambda c: R(c.ck, c.x0, 2, generator=42))  # fmt: skip
api("rollout/generator=str", InputTypeError, ("generator", "'seed'"),
    lambda c: R(c.ck, c.x0, 2, generator="seed"))  # fmt: skip
HAS_CUDA = None if NO_CUDA else "CUDA present"
api("rollout/device=cuda", InputError, ("device", "'cuda'", "no CUDA"),
    lambda c: R(c.ck, c.x0, 2, device="cuda"), skip=HAS_CUDA)  # fmt: skip
api("rollout/device=banana", InputError, ("device", "'banana'"),
    lambda c: R(c.ck, c.x0, 2, device="banana"))  # fmt: skip
api("rollout/device=3", InputTypeError, ("device", "3"), lambda c: R(c.ck, c.x0, 2, device=3))
api("rollout/eta=-1", InputError, ("eta", ">= 0"), lambda c: R(c.ck, c.x0, 2, eta=-1.0))
api("rollout/eta=nan", InputError, ("eta", "finite"), lambda c: R(c.ck, c.x0, 2, eta=float("nan")))
api("rollout/clip_x0=0", ValueError, ("clip_x0", "> 0", "0.0"),
    lambda c: R(c.ck, c.x0, 2, clip_x0=0.0))  # fmt: skip
api("rollout/clip_x0=-1", ValueError, ("clip_x0", "> 0"), lambda c: R(c.ck, c.x0, 2, clip_x0=-1))
api("rollout/clip_x0='data'", ValueError, ("clip_x0", "'data'"),
    lambda c: R(c.ck, c.x0, 2, clip_x0="data"))  # fmt: skip
api("rollout/clip_x0 short pair", ValueError, ("clip_x0", f"{D} values"),
    lambda c: R(c.ck, c.x0, 2, clip_x0=([0.0], [1.0])))  # fmt: skip
api("rollout/clip_x0 lo>hi", ValueError, ("clip_x0", "lo <= hi"),
    lambda c: R(c.ck, c.x0, 2, clip_x0=(torch.ones(D), torch.zeros(D))))  # fmt: skip
api("rollout/model=5", InputTypeError, ("model", "int"), lambda c: R(5, c.x0, 2))
api("rollout/model path missing", FileNotFoundError, ("no checkpoint", "nowhere"),
    lambda c: R(c.root / "nowhere", c.x0, 2))  # fmt: skip
api("rollout/not a motion model", InputError, ("model", "Linear"),
    lambda c: R(torch.nn.Linear(D, D), c.x0, 2))  # fmt: skip
api("rollout/bare denoiser, no schedule", InputError, ("schedule",),
    lambda c: R(c.ck.model, c.x0, 2))  # fmt: skip

# --- rollout: the start ----------------------------------------------------------------------
api("rollout/batch 0", InputError, ("init_states", "at least one frame", "(0, 51)"),
    lambda c: R(c.ck, torch.zeros(0, D), 2))  # fmt: skip
api("rollout/D=87", InputError, ("init_states", "(C, 51)", "(1, 87)", "7-joint", "Hips"),
    lambda c: R(c.ck, torch.zeros(1, 87), 2))  # fmt: skip
api("rollout/D not 3+12J", InputError, ("init_states", "(1, 50)", "no skeleton"),
    lambda c: R(c.ck, torch.zeros(1, 50), 2))  # fmt: skip
api("rollout/3-D", InputError, ("init_states", "shape", "(1, 1, 51)"),
    lambda c: R(c.ck, torch.zeros(1, 1, D), 2))  # fmt: skip
api("rollout/1e30", InputError, ("init_states", "feature units", "1e+30"),
    lambda c: R(c.ck, torch.full((D,), 1e30), 2))  # fmt: skip
api("rollout/NaN", InputError, ("init_states", "finite", "character 1"),
    lambda c: R(c.ck, torch.stack([c.x0, c.x0 * float("nan")]), 2))  # fmt: skip
api("rollout/Inf", InputError, ("init_states", "finite", "inf"),
    lambda c: R(c.ck, torch.full((D,), float("inf")), 2))  # fmt: skip
api("rollout/str", InputTypeError, ("init_states", "'abc'"), lambda c: R(c.ck, "abc", 2))
api("rollout/None", InputTypeError, ("init_states", "None"), lambda c: R(c.ck, None, 2))
api("rollout/bool frames", InputTypeError, ("init_states", "torch.bool"),
    lambda c: R(c.ck, torch.ones(D, dtype=torch.bool), 2))  # fmt: skip
api("rollout/ragged list", InputTypeError, ("init_states",),
    lambda c: R(c.ck, [[0.0] * D, [0.0]], 2))  # fmt: skip
api("rollout/start_pose=5", InputTypeError, ("start_pose", "StartPose", "5"),
    lambda c: R(c.ck, c.x0, 2, start_pose=5))  # fmt: skip
api("rollout/start_pose dict keys", InputTypeError, ("start_pose", "'xy'"),
    lambda c: R(c.ck, c.x0, 2, start_pose={"x": 0}))  # fmt: skip
api("rollout/start_pose xy shape", InputError, ("start_pose", "xy", "(3, 2)"),
    lambda c: R(c.ck, c.x0, 2, start_pose={"xy": torch.zeros(3, 2), "heading": 0.0}))  # fmt: skip
api("rollout/start_pose NaN", InputError, ("start_pose", "finite"),
    lambda c: R(c.ck, c.x0, 2, start_pose={"xy": [float("nan"), 0.0], "heading": 0.0}))  # fmt: skip

# --- rollout: skeletons ----------------------------------------------------------------------
api("rollout/clip of another skeleton", MismatchError,
    ("init_states", "another skeleton", "pelvis", "Hips", "first difference", "joint 0"),
    lambda c: R(c.ck, c.other, 2))  # fmt: skip
api("rollout/start pose of another skeleton", MismatchError,
    ("init_states", "another skeleton", "'pelvis'", "'Hips'"),
    lambda c: R(c.ck, c.other_x0, 2, start_pose=start_pose_of(c.other, 7)))  # fmt: skip
api("rollout/clip of a 3-joint skeleton", MismatchError, ("3-joint skeleton", "4-joint skeleton"),
    lambda c: R(c.ck, c.three, 2))  # fmt: skip
api("rollout/clip at 60 fps", MismatchError, ("60 frames per second", "30", "resample_clip"),
    lambda c: R(c.ck, c.at60, 2))  # fmt: skip
api("rollout/one-frame clip", InputError, ("init_states", "at least 2 frames"),
    lambda c: R(c.ck, c.clip.slice(0, 1), 2))  # fmt: skip
api("autoregress/n_frames=0", InputError, ("n_frames", ">= 1"),
    lambda c: autoregress(lambda f, x: x, torch.zeros(1, 2), 0))  # fmt: skip

# --- control ---------------------------------------------------------------------------------
TG = torch.zeros(3, D)  # 3 target frames


def mask(value=1, frames: int | None = None):
    return torch.full((D,) if frames is None else (frames, D), value)


IP = inpaint
api("inpaint/mask=2", InputError, ("mask", "binary", "2"), lambda c: IP(c.ck, c.x0, TG, mask(2)))
api("inpaint/mask=-1", InputError, ("mask", "binary", "-1"),
    lambda c: IP(c.ck, c.x0, TG, mask(-1)))  # fmt: skip
api("inpaint/mask=0.5", InputError, ("mask", "binary", "0.5"),
    lambda c: IP(c.ck, c.x0, TG, mask(0.5)))  # fmt: skip
api("inpaint/mask=str", InputTypeError, ("mask", "'yes'"), lambda c: IP(c.ck, c.x0, TG, "yes"))
api("inpaint/mask wrong D", ValueError, ("mask", "last dim", "D=51"),
    lambda c: IP(c.ck, c.x0, TG, torch.ones(5)))  # fmt: skip
api("inpaint/mask wrong frames", ValueError, ("mask", "3 frames"),
    lambda c: IP(c.ck, c.x0, TG, mask(1, frames=2)))  # fmt: skip
api("inpaint/targets wrong D", InputError, ("targets", "(F, 51)", "(3, 50)"),
    lambda c: IP(c.ck, c.x0, torch.zeros(3, 50), mask()))  # fmt: skip
api("inpaint/targets no frames", InputError, ("targets", "at least one frame"),
    lambda c: IP(c.ck, c.x0, torch.zeros(0, D), mask()))  # fmt: skip
api("inpaint/targets Inf", InputError, ("targets", "finite", "inf"),
    lambda c: IP(c.ck, c.x0, torch.full((3, D), float("inf")), mask()))  # fmt: skip
api("inpaint/targets NaN under the mask", ValueError, ("NaN/Inf where the mask is set", "frame 1"),
    lambda c: IP(c.ck, c.x0, torch.full((3, D), float("nan")), mask()))  # fmt: skip
api("inpaint/targets 1e30", InputError, ("targets", "feature units"),
    lambda c: IP(c.ck, c.x0, torch.full((3, D), 1e30), mask()))  # fmt: skip
api("inpaint/t_stop=2.5", InputTypeError, ("t_stop", "2.5"),
    lambda c: IP(c.ck, c.x0, TG, mask(), t_stop=2.5))  # fmt: skip
api("inpaint/t_stop=99", InputError, ("t_stop", f"[-1, {T - 1}]", "99"),
    lambda c: IP(c.ck, c.x0, TG, mask(), t_stop=99))  # fmt: skip
api("inpaint/t_stop=-5", InputError, ("t_stop", "-5"),
    lambda c: IP(c.ck, c.x0, TG, mask(), t_stop=-5))  # fmt: skip
api("inpaint/t_stop count", InputError, ("t_stop", "F=3", "2 values"),
    lambda c: IP(c.ck, c.x0, TG, mask(), t_stop=[0, 1]))  # fmt: skip
api("inpaint/start wrong D", InputError, ("start", "(51,)", "(7,)"),
    lambda c: IP(c.ck, torch.zeros(7), TG, mask()))  # fmt: skip
api("inpaint/generator=42", InputTypeError, ("generator", "42"),
    lambda c: IP(c.ck, c.x0, TG, mask(), 42))  # fmt: skip
api("inpaint/clip of another skeleton", MismatchError, ("start", "another skeleton", "pelvis"),
    lambda c: IP(c.ck, c.other, TG, mask()))  # fmt: skip

IB = inbetween
api("inbetween/at=2.7", InputTypeError, ("at", "integer", "2.7"),
    lambda c: IB(c.ck, c.x0, c.x0, 3, at=2.7))  # fmt: skip
api("inbetween/at=0", InputError, ("at", ">= 1", "0"), lambda c: IB(c.ck, c.x0, c.x0, 3, at=0))
api("inbetween/at beyond horizon", ValueError, ("beyond the horizon", "n_frames=3"),
    lambda c: IB(c.ck, c.x0, c.x0, 3, at=5))  # fmt: skip
api("inbetween/at decreasing", ValueError, ("increasing", "[3, 2]"),
    lambda c: IB(c.ck, c.x0, torch.stack([c.x0, c.x0]), 3, at=[3, 2]))  # fmt: skip
api("inbetween/at count", ValueError, ("one frame per keyframe", "K=2"),
    lambda c: IB(c.ck, c.x0, torch.stack([c.x0, c.x0]), 3, at=[3]))  # fmt: skip
api("inbetween/at None, K=2", InputError, ("at must give", "K=2"),
    lambda c: IB(c.ck, c.x0, torch.stack([c.x0, c.x0]), 3))  # fmt: skip
api("inbetween/at str", InputTypeError, ("at", "'3'"), lambda c: IB(c.ck, c.x0, c.x0, 3, at="3"))
api("inbetween/keyframe wrong D", InputError, ("keyframe", "(51,)", "(50,)"),
    lambda c: IB(c.ck, c.x0, torch.zeros(50), 3))  # fmt: skip
api("inbetween/keyframe NaN", InputError, ("keyframe", "finite"),
    lambda c: IB(c.ck, c.x0, c.x0 * float("nan"), 3))  # fmt: skip
api("inbetween/keyframe 1e30", InputError, ("keyframe", "feature units"),
    lambda c: IB(c.ck, c.x0, torch.full((D,), 1e30), 3))  # fmt: skip
api("inbetween/n_frames=True", InputTypeError, ("n_frames", "True"),
    lambda c: IB(c.ck, c.x0, c.x0, True))  # fmt: skip
api("inbetween/n_frames=-1", InputError, ("n_frames", "-1"), lambda c: IB(c.ck, c.x0, c.x0, -1))
api("inbetween/clip of another skeleton", MismatchError, ("start", "pelvis", "Hips"),
    lambda c: IB(c.ck, c.other, c.x0, 3))  # fmt: skip
api("lerp_inbetween/n_frames=0", InputError, ("n_frames", ">= 1"),
    lambda c: lerp_inbetween(c.ck, c.x0, c.x0, 0))  # fmt: skip


def score(future):
    return -future.root_xy[..., -1, 0]


BS = beam_search
api("beam_search/pool=0", InputError, ("pool", ">= 1", "0"),
    lambda c: BS(c.ck, c.x0, score, 2, pool=0))  # fmt: skip
api("beam_search/horizon=2.5", InputTypeError, ("horizon", "2.5"),
    lambda c: BS(c.ck, c.x0, score, 2, horizon=2.5))  # fmt: skip
api("beam_search/commit>horizon", ValueError, ("commit", "horizon=1"),
    lambda c: BS(c.ck, c.x0, score, 2, commit=2))  # fmt: skip
api("beam_search/score_fn=3", InputTypeError, ("score_fn", "callable", "3"),
    lambda c: BS(c.ck, c.x0, 3, 2))  # fmt: skip
api("beam_search/stop_fn=3", InputTypeError, ("stop_fn", "callable"),
    lambda c: BS(c.ck, c.x0, score, 2, stop_fn=3))  # fmt: skip
api("beam_search/generator=42", InputTypeError, ("generator", "42"),
    lambda c: BS(c.ck, c.x0, score, 2, generator=42))  # fmt: skip
api("beam_search/start NaN", InputError, ("start", "finite"),
    lambda c: BS(c.ck, c.x0 * float("nan"), score, 2))  # fmt: skip
api("beam_search/n_frames=0", InputError, ("n_frames", ">= 1"),
    lambda c: BS(c.ck, c.x0, score, 0))  # fmt: skip
api("Sampler.load/steps=0", InputError, ("steps", ">= 1"),
    lambda c: Sampler.load(c.ck, steps=0))  # fmt: skip
api("Sampler.load/steps>T", InputError, ("steps", f"T={T}"),
    lambda c: Sampler.load(c.ck, steps=9))  # fmt: skip
api("Sampler.load/eta=-1", InputError, ("eta", ">= 0"),
    lambda c: Sampler.load(c.ck, eta=-1))  # fmt: skip
api("Sampler.load/device=banana", InputError, ("device", "banana"),
    lambda c: Sampler.load(c.ck, device="banana"))  # fmt: skip
api("Sampler.load/model=5", InputTypeError, ("model", "int"), lambda c: Sampler.load(5))
api("Sampler.load/clip_x0=0", ValueError, ("clip_x0", "> 0"),
    lambda c: Sampler.load(c.ck, clip_x0=0))  # fmt: skip

# --- motion helpers --------------------------------------------------------------------------
api("start_pose_of/frame beyond clip", InputError, ("frame", "99"),
    lambda c: start_pose_of(c.clip, 99))  # fmt: skip
api("start_pose_of/frame=1.5", InputTypeError, ("frame", "1.5"),
    lambda c: start_pose_of(c.clip, 1.5))  # fmt: skip
api("resample_clip/fps=0", InputError, ("fps", "> 0"), lambda c: resample_clip(c.clip, 0))
api("resample_clip/fps=1e9", InputError, ("fps", "1000000 frames"),
    lambda c: resample_clip(c.clip, 1e9))  # fmt: skip
api("resample_clip/fps='30'", InputTypeError, ("fps", "'30'"),
    lambda c: resample_clip(c.clip, "30"))  # fmt: skip
api("initial_state/unknown clip", InputError, ("clip", "'nosuchclip'", "sway"),
    lambda c: initial_state(c.ck, "nosuchclip"))  # fmt: skip
api("initial_state/frame=-3", InputError, ("frame", ">= 0", "-3"),
    lambda c: initial_state(c.ck, "sway", -3))  # fmt: skip
api("initial_state/frame beyond clip", InputError, ("frame", "[1, 11]", "9999"),
    lambda c: initial_state(c.ck, "sway", 9999))  # fmt: skip

# --- BVH files -------------------------------------------------------------------------------
BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 150 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0333333
0 90 0 0 0 0 0 0 0
0 90 0 0 0 0 0 0 0
0 90 0 0 0 0 0 0 0
"""


def bvh_row(id: str, error, words: tuple[str, ...], edit, **kw) -> None:
    """A row that loads ``edit(BVH)`` (text, or bytes) from a file named after the row."""

    def run(c):
        path = c.root / (re.sub(r"\W+", "_", id) + ".bvh")
        data = edit(BVH)
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
        return load_bvh(path, **kw)

    where = ("bvh_",) if error is BVHError else ()  # a file's fault names the file
    ROWS.append(Row(id, run, error, (*where, *words)))


def sub(old: str, new: str, count: int = 1):
    return lambda text: text.replace(old, new, count)


bvh_row("bvh/Frame Time 1e6", BVHError, ("Frame Time 1e+06 s", "1 to 1000"),
        sub("0.0333333", "1e6"))  # fmt: skip
bvh_row("bvh/Frame Time 1e-9", BVHError, ("Frame Time 1e-09 s", "frames per second"),
        sub("0.0333333", "1e-9"))  # fmt: skip
bvh_row("bvh/Frame Time 0", BVHError, (":18:", "Frame Time > 0"), sub("0.0333333", "0"))
bvh_row("bvh/Frame Time -1", BVHError, (":18:", "Frame Time > 0"), sub("0.0333333", "-1"))
bvh_row("bvh/Frame Time abc", BVHError, (":18:", "Frame Time: <seconds>"),
        sub("0.0333333", "abc"))  # fmt: skip
bvh_row("bvh/Frames x", BVHError, (":17:", "Frames: <integer>"), sub("Frames: 3", "Frames: x"))
bvh_row("bvh/too few frames", BVHError, ("expected 5 frames", "line 17"),
        sub("Frames: 3", "Frames: 5"))  # fmt: skip
bvh_row("bvh/short row", BVHError, (":19:", "9 channel values", "got 3"),
        sub("0 90 0 0 0 0 0 0 0", "0 90 0"))  # fmt: skip
bvh_row("bvh/word in a row", BVHError, (":19:", "expected a number", "'abc'"),
        sub("0 90 0 0 0 0 0 0 0", "0 90 0 0 0 0 0 0 abc"))  # fmt: skip
bvh_row("bvh/NaN in a row", BVHError, (":19:", "NaN/Inf"),
        sub("0 90 0 0 0 0 0 0 0", "0 90 0 0 0 0 0 0 nan"))  # fmt: skip
bvh_row("bvh/OFFSET 1e308", BVHError, ("cannot guess the units", "scale="),
        sub("OFFSET 0 10 0", "OFFSET 0 1e308 0"))  # fmt: skip
bvh_row("bvh/all-zero offsets", BVHError, ("no vertical extent", "scale="),
        lambda t: t.replace("OFFSET 0 10 0", "OFFSET 0 0 0").replace("0 150 0", "0 0 0")
        .replace("0 90 0 0", "0 0 0 0"))  # fmt: skip
bvh_row("bvh/OFFSET abc", BVHError, (":8:", "an OFFSET number", "'abc'"),
        sub("OFFSET 0 10 0", "OFFSET 0 abc 0"))  # fmt: skip
bvh_row("bvh/duplicate joint", BVHError, (":6:", "'Hips'", "used twice"),
        sub("JOINT Chest", "JOINT Hips"))  # fmt: skip
bvh_row("bvh/no HIERARCHY", BVHError, (":1:", "HIERARCHY"), sub("HIERARCHY", "HIERARCHIE"))
bvh_row("bvh/empty file", BVHError, (":1:", "empty file"), lambda t: "")
bvh_row("bvh/no MOTION", BVHError, ("MOTION",), lambda t: t.split("MOTION")[0])
bvh_row("bvh/bad channel", BVHError, (":5:", "channel name", "'Wrotation'"),
        sub("Zrotation Xrotation Yrotation", "Wrotation Xrotation Yrotation"))  # fmt: skip
bvh_row(
    "bvh/root without channels",
    BVHError,
    (":5:", "CHANNELS"),
    sub("  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n", ""),
)
bvh_row("bvh/unclosed brace", BVHError, ("'}'",), lambda t: t.replace("}\nMOTION", "MOTION"))
bvh_row("bvh/NUL bytes", BVHError, ("not a text file",), lambda t: b"\x00\x01" + t.encode())
bvh_row("bvh/text after the frames", BVHError, (":22:", "end of file"),
        lambda t: t + "0 90 0 0 0 0 0 0 0\n")  # fmt: skip
bvh_row("bvh/resampled too long", BVHError, ("more than 1000000 frames",),
        lambda t: t.replace("Frame Time: 0.0333333", "Frame Time: 1")
        .replace("Frames: 3", "Frames: 4000") + "0 90 0 0 0 0 0 0 0\n" * 3997,
        fps=1000)  # fmt: skip
bvh_row("bvh/fps=0", InputError, ("fps", "[1.0, 1000.0]"), lambda t: t, fps=0)
bvh_row("bvh/fps='30'", InputTypeError, ("fps", "'30'"), lambda t: t, fps="30")
bvh_row("bvh/scale=0", InputError, ("scale", "> 0"), lambda t: t, scale=0)
bvh_row("bvh/scale=True", InputTypeError, ("scale", "True"), lambda t: t, scale=True)
bvh_row("bvh/scale=nan", InputError, ("scale", "finite"), lambda t: t, scale=float("nan"))
api("bvh/missing file", FileNotFoundError, ("no BVH file", "missing.bvh"),
    lambda c: load_bvh(c.root / "missing.bvh"))  # fmt: skip
api("bvh/path=5", InputTypeError, ("path", "5"), lambda c: load_bvh(5))


@row("bvh/folder of two skeletons", BVHError, "different skeletons", "joint 1")
def _two_skeletons(c):
    folder = c.root / "two"
    folder.mkdir(exist_ok=True)
    save_bvh(folder / "a.bvh", make_clip(MODEL_JOINTS))
    save_bvh(folder / "b.bvh", make_clip(["Hips", "Torso", "Head", "Leg"]))
    return load_bvh(folder)


@row("bvh/empty folder", FileNotFoundError, "no .bvh files")
def _empty_folder(c):
    (c.root / "empty").mkdir(exist_ok=True)
    return load_bvh(c.root / "empty")


# --- checkpoints -----------------------------------------------------------------------------
def header_of(data: bytes) -> tuple[dict, bytes]:
    n = int.from_bytes(data[:8], "little")
    return json.loads(data[8 : 8 + n]), data[8 + n :]


def with_header(header: dict, rest: bytes) -> bytes:
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 8)
    return len(text).to_bytes(8, "little") + text + rest


def edit_meta(edit):
    """The checkpoint's bytes with its metadata JSON edited by ``edit(meta)``."""

    def make(c) -> bytes:
        header, rest = header_of(c.weights)
        meta = json.loads(header["__metadata__"]["minimdm"])
        edit(meta)
        header["__metadata__"]["minimdm"] = json.dumps(meta)
        return with_header(header, rest)

    return make


def set_key(path: str, value):
    def edit(meta):
        *keys, last = path.split(".")
        d = meta
        for k in keys:
            d = d[k]
        if value is KeyError:
            del d[last]
        else:
            d[last] = value

    return edit_meta(edit)


def bad_header_json(c) -> bytes:
    header, rest = header_of(c.weights)
    header["__metadata__"]["minimdm"] = "{not json"
    return with_header(header, rest)


def no_metadata(c) -> bytes:
    header, rest = header_of(c.weights)
    del header["__metadata__"]
    return with_header(header, rest)


def missing_tensor(c) -> bytes:
    state = {k: v for k, v in c.ck.model.state_dict().items() if not k.endswith("bias")}
    header, _ = header_of(c.weights)
    return st_save({k: v.contiguous() for k, v in state.items()}, header["__metadata__"])


CORRUPT: dict[str, tuple[Callable[[Any], bytes], tuple[str, ...]]] = {
    "zero bytes": (lambda c: b"", ("empty (0 bytes)",)),
    "truncated": (lambda c: c.weights[: len(c.weights) // 2], ("truncated",)),
    "5 bytes": (lambda c: c.weights[:5], ("truncated", "5 bytes")),
    "random bytes": (lambda c: bytes(range(256)) * 20, ("not a safetensors file",)),
    "pickle": (lambda c: pickle.dumps({"w": [1, 2]}), ("pickle", "never loads")),
    "torch.save zip": (lambda c: b"PK\x03\x04" + bytes(100), ("pickle", "never loads")),
    "bad header JSON": (bad_header_json, ("'minimdm' header", "not valid JSON")),
    "no minimdm metadata": (no_metadata, ("not a minimdm checkpoint",)),
    "no model entry": (set_key("model", KeyError), ("no 'model' entry",)),
    "width mismatch": (set_key("model.config.width", 8), ("shape", "the network needs")),
    "missing tensor": (missing_tensor, ("missing tensors", "bias")),
    "unknown config key": (set_key("model.config.bogus", 1), ("bogus", "does not build")),
    "unknown kind": (set_key("model.kind", "nosuch"), ("model kind", "'nosuch'")),
    "other format": (set_key("format", "other/9"), ("format", "'other/9'")),
    # issue 27: contents out of bounds, refused at load time with the file named
    "T 1e9": (set_key("diffusion.T", 10**9), ("diffusion.T", "[1, 10000]", "1000000000")),
    "T 0": (set_key("diffusion.T", 0), ("diffusion.T", "[1, 10000]")),
    "width 1e9": (set_key("model.config.width", 10**9), ("model.config.width", "65536")),
    "predicts 'w'": (set_key("diffusion.predicts", "w"), ("diffusion.predicts", "'w'")),
    "int32 weights": (lambda c: retyped(c, torch.int32), ("stored as int32", "floating point")),
    "bool weights": (lambda c: retyped(c, torch.bool), ("stored as bool", "floating point")),
    "uint8 weights": (lambda c: retyped(c, torch.uint8), ("stored as uint8", "floating point")),
    "float16 weights, not recorded": (
        lambda c: retyped(c, torch.float16), ("stored as float16", "storage 'float32'")),
    "NaN weights": (lambda c: retyped(c, torch.float32, nan=True), ("holds NaN or Inf",)),
    "normalizer std 0": (edit_meta(lambda m: m["normalizer"]["std"].__setitem__(0, 0.0)),
                         ("normalizer.std[0]", "(0, 1e+06]", "got 0")),
    "normalizer std -1": (edit_meta(lambda m: m["normalizer"]["std"].__setitem__(2, -1.0)),
                          ("normalizer.std[2]", "got -1")),
    "normalizer std 1e30": (edit_meta(lambda m: m["normalizer"]["std"].__setitem__(1, 1e30)),
                            ("normalizer.std[1]", "got 1e+30")),
    "normalizer mean NaN": (edit_meta(lambda m: m["normalizer"]["mean"].__setitem__(0, NAN)),
                            ("normalizer.mean[0]", "finite", "nan")),
    "clip_x0 -1": (set_key("diffusion.clip_x0", -1.0), ("diffusion.clip_x0", "> 0", "-1")),
    "clip_x0 lo > hi": (set_key("diffusion.clip_x0", [[1.0] * D, [0.0] * D]),
                        ("diffusion.clip_x0", "lo <= hi", "feature 0")),
    "fps 0": (set_key("config.fps", 0), ("config.fps", "[1, 1000]")),
    "storage 'int4'": (set_key("storage", "int4"), ("storage", "'int4'")),
}  # fmt: skip


def retyped(c, dtype: torch.dtype, nan: bool = False) -> bytes:
    """The checkpoint's bytes with every weight stored as ``dtype`` (one NaN with ``nan``)."""
    state = {k: v.to(dtype).clone() for k, v in c.ck.model.state_dict().items()}  # a copy
    if nan:
        next(iter(state.values())).view(-1)[0] = float("nan")
    header, _ = header_of(c.weights)
    return st_save(state, header["__metadata__"])


def corrupt_folder(c, name: str) -> Path:
    make, _ = CORRUPT[name]
    folder = c.root / ("corrupt_" + re.sub(r"\W+", "_", name))
    folder.mkdir(exist_ok=True)
    (folder / "model.safetensors").write_bytes(make(c))
    return folder


for _name, (_, _words) in CORRUPT.items():
    api(f"checkpoint/{_name}", CheckpointError, ("model.safetensors", "corrupt_", *_words),
        lambda c, n=_name: load_checkpoint(corrupt_folder(c, n)))  # fmt: skip
for _name in ("zero bytes", "pickle", "bad header JSON", "width mismatch", "unknown config key"):
    ROWS.append(Row(f"cli/sample checkpoint {_name}", lambda c, n=_name: main([
        "sample", "--checkpoint", str(corrupt_folder(c, n)), "--frames", "2",
        "--out", str(c.root / "x.npz")]), "exit 2",
        ("minimdm sample: error:", "corrupt_", *CORRUPT[_name][1])))  # fmt: skip


@row("checkpoint/train state zero bytes", CheckpointError, "model.train.safetensors", "empty")
def _train_state(c):
    folder = c.root / "train_state"
    folder.mkdir(exist_ok=True)
    (folder / "model.train.safetensors").write_bytes(b"")
    return load_train_state(folder)


api("checkpoint/expected skeleton", CheckpointMismatchError, ("skeleton", "first difference"),
    lambda c: load_checkpoint(c.ckdir, expected_skeleton=c.other.skeleton))  # fmt: skip
api("checkpoint/expected layout", CheckpointMismatchError, ("feature layout", "joint_names"),
    lambda c: load_checkpoint(c.ckdir, expected_layout=FeatureLayout(tuple(OTHER_JOINTS))),
    )  # fmt: skip
api("checkpoint/missing", FileNotFoundError, ("no checkpoint", "nowhere"),
    lambda c: load_checkpoint(c.root / "nowhere"))  # fmt: skip

BAD_YAML = "T: 5\n  width: 32\n"  # a mapping inside a value: line 2 is not YAML

# --- training and configs --------------------------------------------------------------------
api("train_amdm/out_dir is a file", InputError, ("out_dir", "a_file", "is a file"),
    lambda c: train_amdm(TrainConfig(), c.root / "a_file"))  # fmt: skip
api("train_amdm/out_dir under a file", InputError, ("out_dir", "a_file", "not a folder"),
    lambda c: train_amdm(TrainConfig(), c.root / "a_file" / "sub"))  # fmt: skip
api("train_amdm/config dict", InputTypeError, ("config", "TrainConfig", "dict"),
    lambda c: train_amdm({}, c.root / "out_dir"))  # fmt: skip


def text_file(name: str, text: str):
    def make(c) -> Path:
        path = c.root / name
        path.write_text(text)
        return path

    return make


api("read_log/bad middle line", ValueError, ("log.jsonl:2", "'step'"),
    lambda c: read_log(text_file("log.jsonl", '{"step": 1}\n{oops\n{"step": 3}\n')(c)))  # fmt: skip
api("config/invalid YAML", ValueError, ("bad.yaml:2", "not valid YAML"),
    lambda c: load_config(text_file("bad.yaml", BAD_YAML)(c), TrainConfig))  # fmt: skip
api("config/missing file", FileNotFoundError, ("nope.yaml", "does not exist"),
    lambda c: load_config(c.root / "nope.yaml", TrainConfig))  # fmt: skip
api("config/a folder", FileNotFoundError, ("cfg.yaml", "is a folder"),
    lambda c: load_config(Path(c.root / "cfg.yaml").mkdir(exist_ok=True) or c.root / "cfg.yaml",
                          TrainConfig))  # fmt: skip
api("config/unknown key", ValueError, ("unknown config keys", "['widht']", "width"),
    lambda c: load_config(text_file("typo.yaml", "widht: 5\n")(c), TrainConfig))  # fmt: skip
api("config/wrong type", ValueError, ("T must be int", "'five'"),
    lambda c: load_config(text_file("type.yaml", "T: five\n")(c), TrainConfig))  # fmt: skip
api("config/not a mapping", ValueError, ("list.yaml", "mapping"),
    lambda c: load_config(text_file("list.yaml", "- 1\n- 2\n")(c), TrainConfig))  # fmt: skip
api("config/suffix", ValueError, ("cfg.txt", ".yaml"),
    lambda c: load_config(text_file("cfg.txt", "T: 5\n")(c), TrainConfig))  # fmt: skip


# --- the command line ------------------------------------------------------------------------
def cli(id: str, words: tuple[str, ...], argv, skip: str | None = None) -> None:
    """A row that runs ``minimdm ARGV``; it must exit with 2 and print one error line."""
    ROWS.append(Row(id, lambda c: main(argv(c)), "exit 2", words, skip))


def sample(c, *extra: str, out: str = "x.npz") -> list[str]:
    return ["sample", "--checkpoint", c.ckdir, "--frames", "2", "--out", str(c.root / out), *extra]


SHIPPED_AAMDM = Path(__file__).resolve().parent.parent / "checkpoints" / "aamdm"
NO_AAMDM = None if SHIPPED_AAMDM.exists() else "no shipped aamdm checkpoint"

cli("cli/sample --device banana", ("minimdm sample: error:", "--device", "'banana'"),
    lambda c: sample(c, "--device", "banana"))  # fmt: skip
cli("cli/sample --device cuda", ("minimdm sample: error:", "--device", "no CUDA"),
    lambda c: sample(c, "--device", "cuda"), skip=None if NO_CUDA else "CUDA present")  # fmt: skip
cli("cli/sample --frames -5", ("minimdm sample: error:", "--frames", "[1, 1000000]", "-5"),
    lambda c: ["sample", "--checkpoint", c.ckdir, "--frames", "-5", "--out", "x.npz"])  # fmt: skip
cli("cli/sample --frames abc", ("minimdm sample: error:", "--frames", "'abc'"),
    lambda c: ["sample", "--checkpoint", c.ckdir, "--frames", "abc", "--out", "x.npz"])  # fmt: skip
cli("cli/sample --samples 0", ("minimdm sample: error:", "--samples"),
    lambda c: sample(c, "--samples", "0"))  # fmt: skip
cli("cli/sample --steps 2.5", ("minimdm sample: error:", "--steps", "'2.5'"),
    lambda c: sample(c, "--steps", "2.5"))  # fmt: skip
cli("cli/sample --steps 99", ("minimdm sample: error:", "steps", f"T={T}"),
    lambda c: sample(c, "--steps", "99"))  # fmt: skip
cli("cli/sample --seed -1", ("minimdm sample: error:", "--seed", "integer in [0, ", "-1"),
    lambda c: sample(c, "--seed", "-1"))  # fmt: skip
cli("cli/sample --out a folder", ("minimdm sample: error:", "--out", "folder"),
    lambda c: sample(c, out="folder.npz"))  # fmt: skip
cli("cli/sample --out under a file", ("minimdm sample: error:", "--out", "a_file", "not a folder"),
    lambda c: sample(c, out="a_file/x.npz"))  # fmt: skip
cli("cli/sample --out unwritable", ("minimdm sample: error:", "--out", "cannot write"),
    lambda c: ["sample", "--checkpoint", c.ckdir, "--frames", "2",
               "--out", "/proc/minimdm/x.npz"])  # fmt: skip
cli("cli/sample --out .txt", ("minimdm sample: error:", "--out must end in", "'x.txt'"),
    lambda c: sample(c, out="x.txt"))  # fmt: skip
cli("cli/sample --start nosuchclip", ("minimdm sample: error:", "'nosuchclip'", "sway"),
    lambda c: sample(c, "--start", "nosuchclip"))  # fmt: skip
cli("cli/sample --start sway:-3", ("minimdm sample: error:", "--start", "FRAME >= 1", "sway:-3"),
    lambda c: sample(c, "--start", "sway:-3"))  # fmt: skip
cli("cli/sample --start sway:9999", ("minimdm sample: error:", "frame", "9999"),
    lambda c: sample(c, "--start", "sway:9999"))  # fmt: skip
cli("cli/sample --checkpoint missing", ("minimdm sample: error:", "no checkpoint"),
    lambda c: ["sample", "--checkpoint", str(c.root / "none"), "--frames", "2",
               "--out", str(c.root / "x.npz")])  # fmt: skip
cli("cli/sample an AAMDM checkpoint", ("minimdm sample: error:", "kind 'aamdm_motion'", "amdm"),
    lambda c: ["sample", "--checkpoint", str(SHIPPED_AAMDM), "--frames", "2",
               "--out", str(c.root / "x.npz")], skip=NO_AAMDM)  # fmt: skip
cli("cli/eval an AAMDM checkpoint", ("minimdm eval: error:", "kind 'aamdm_motion'"),
    lambda c: ["eval", "--checkpoint", str(SHIPPED_AAMDM)], skip=NO_AAMDM)  # fmt: skip
cli("cli/eval --device banana", ("minimdm eval: error:", "--device", "'banana'"),
    lambda c: ["eval", "--checkpoint", c.ckdir, "--device", "banana"])  # fmt: skip
cli("cli/eval --samples 1", ("minimdm eval: error:", "--samples", "[2, 10000]"),
    lambda c: ["eval", "--checkpoint", c.ckdir, "--samples", "1"])  # fmt: skip
cli("cli/train invalid YAML", ("minimdm train: error:", "bad.yaml:2", "not valid YAML"),
    lambda c: ["train", str(text_file("bad.yaml", BAD_YAML)(c)),
               "--out", str(c.root / "run")])  # fmt: skip
cli("cli/train missing config", ("minimdm train: error:", "nope.yaml", "does not exist"),
    lambda c: ["train", str(c.root / "nope.yaml"), "--out", str(c.root / "run")])  # fmt: skip
cli("cli/train --out a file", ("minimdm train: error:", "--out", "is a file"),
    lambda c: ["train", str(text_file("ok.yaml", "T: 4\n")(c)),
               "--out", str(c.root / "a_file")])  # fmt: skip
cli("cli/train --set without =", ("minimdm train: error:", "--set expects KEY=VALUE"),
    lambda c: ["train", str(text_file("ok.yaml", "T: 4\n")(c)), "--out", str(c.root / "run"),
               "--set", "width"])  # fmt: skip
cli("cli/train --set unknown key", ("minimdm train: error:", "unknown config keys", "widht"),
    lambda c: ["train", str(text_file("ok.yaml", "T: 4\n")(c)), "--out", str(c.root / "run"),
               "--set", "widht=5"])  # fmt: skip
cli("cli/train --device banana", ("minimdm train: error:", "--device", "'banana'"),
    lambda c: ["train", str(text_file("ok.yaml", "T: 4\n")(c)), "--device", "banana"])  # fmt: skip
cli("cli/train device in config", ("minimdm train: error:", "device (of the config)", "banana"),
    lambda c: ["train", str(text_file("dev.yaml", "device: banana\n")(c)),
               "--out", str(c.root / "run")])  # fmt: skip
cli("cli/train --threads 0", ("minimdm train: error:", "--threads", ">= 1"),
    lambda c: ["train", "configs/amdm.yaml", "--threads", "0"])  # fmt: skip
cli("cli/train --steps 0", ("minimdm train: error:", "--steps", ">= 1"),
    lambda c: ["train", "configs/amdm.yaml", "--steps", "0"])  # fmt: skip
cli("cli/rl invalid YAML", ("minimdm rl: error:", "bad.yaml:2", "not valid YAML"),
    lambda c: ["rl", str(text_file("bad.yaml", BAD_YAML)(c)),
               "--out", str(c.root / "run")])  # fmt: skip
cli("cli/rl --out a file", ("minimdm rl: error:", "--out", "is a file"),
    lambda c: ["rl", "configs/rl_target.yaml", "--out", str(c.root / "a_file")])  # fmt: skip
cli("cli/rl missing config", ("minimdm rl: error:", "nope.yaml", "does not exist"),
    lambda c: ["rl", str(c.root / "nope.yaml"), "--out", str(c.root / "run")])  # fmt: skip
cli("cli/rl --threads 0", ("minimdm rl: error:", "--threads", ">= 1"),
    lambda c: ["rl", "configs/rl_target.yaml", "--threads", "0"])  # fmt: skip
cli("cli/rl negative motion penalty", ("minimdm rl: error:", "motion_penalty", ">= 0", "-1"),
    lambda c: ["rl", "configs/rl_target.yaml", "--set", "motion_penalty=-1",
               "--out", str(c.root / "run")])  # fmt: skip
api("rl/RLConfig action_penalty=nan", InputError, ("action_penalty", "finite", "nan"),
    lambda c: RLConfig(action_penalty=float("nan")))  # fmt: skip
api("rl/RLConfig motion_penalty='high'", InputTypeError, ("motion_penalty", "'high'"),
    lambda c: RLConfig(motion_penalty="high"))  # fmt: skip
api("rl/RLConfig observe='body'", InputError, ("observe", "'frame', 'root'", "'body'"),
    lambda c: RLConfig(observe="body"))  # fmt: skip
cli("cli/rl --set observe=all", ("minimdm rl: error:", "observe", "'all'"),
    lambda c: ["rl", "configs/rl_target.yaml", "--set", "observe=all",
               "--out", str(c.root / "run")])  # fmt: skip
api("rl/load_steering of a motion model", ValueError, ("amdm", "not a steering policy"),
    lambda c: load_steering("amdm"))  # fmt: skip
cli("cli/data download unknown", ("minimdm data download: error:", "'nosuchcorpus'"),
    lambda c: ["data", "download", "nosuchcorpus"])  # fmt: skip
cli("cli/no command", ("minimdm: error:",), lambda c: [])
cli("cli/unknown command", ("minimdm: error:", "'fly'"), lambda c: ["fly"])


# --- issue 27: nothing lost ------------------------------------------------------------------
# Training writes to runs/<config stem>/; a folder in the shipped checkpoints/ needs --ship, and
# a folder another live run holds is refused, naming that run.
SHIPPED = Path(__file__).resolve().parent.parent / "checkpoints"
SHIP = ("--out", "shipped checkpoints", "--ship")
OK_YAML = text_file("ok.yaml", "T: 4\n")
for _verb, _config in (("train", "configs/amdm.yaml"), ("rl", "configs/rl_target.yaml"),
                       ("camdm train", "configs/camdm.yaml"),
                       ("camdm classifier", "configs/camdm_classifier.yaml")):  # fmt: skip
    cli(
        f"cli/{_verb} --out checkpoints/ (shipped)",
        (f"minimdm {_verb}: error:", *SHIP),
        lambda c, v=_verb, f=_config: [*v.split(), f, "--out", str(SHIPPED / Path(f).stem)],
    )
cli("cli/train --out '' (the current folder)", ("minimdm train: error:", "--out", "''"),
    lambda c: ["train", str(OK_YAML(c)), "--out", ""])  # fmt: skip
cli("cli/train --out checkpoints/../checkpoints/amdm", ("minimdm train: error:", *SHIP),
    lambda c: ["train", str(OK_YAML(c)), "--out", f"{SHIPPED}/../checkpoints/amdm"])  # fmt: skip
cli(
    "cli/train --out a symlink into checkpoints/",
    ("minimdm train: error:", *SHIP),
    lambda c: ["train", str(OK_YAML(c)), "--out", str(symlink(c, "ckpt_link", SHIPPED)) + "/x"],
)
cli("cli/train --out a new folder in checkpoints/", ("minimdm train: error:", *SHIP),
    lambda c: ["train", str(OK_YAML(c)), "--out", str(SHIPPED / "no_such_run")])  # fmt: skip
ROWS.append(Row("cli/train --out held by a live run",
                lambda c: held(c, ["train", str(OK_YAML(c)), "--out", str(c.root / "held")]),
                "exit 2", ("minimdm train: error:", "in use by another run",
                           f"pid {os.getpid()}", "minimdm train held.yaml")))  # fmt: skip
api("train_amdm/out_dir held by a live run", LockedError, ("held", "in use by another run", "pid"),
    lambda c: held(c, None, lambda: train_amdm(TrainConfig(), c.root / "held")))  # fmt: skip
api("RunLock/held on another machine", LockedError, ("pid 7 on elsewhere", "delete", "run.lock"),
    lambda c: foreign_lock(c))  # fmt: skip
api("atomic_write/full disk", WriteError, ("cannot write", "full.txt", "No space left on device"),
    lambda c: on_a_full_disk(lambda: atomic_write(c.root / "full.txt", "x" * 1000)))  # fmt: skip
ROWS.append(Row("cli/sample --out x.bvh on a full disk",
                lambda c: on_a_full_disk(lambda: main(sample(c, "--quiet", out="full.bvh"))),
                "exit 2", ("minimdm sample: error:", "cannot write", "full.bvh",
                           "No space left on device")))  # fmt: skip
api("data download/not an archive", DownloadError,
    ("neither a zip nor a tar archive", "deleted", "recorded no SHA-256"),
    lambda c: download_not_an_archive(c))  # fmt: skip


def symlink(c, name: str, target: Path) -> Path:
    link = c.root / name
    if not link.is_symlink():
        link.symlink_to(target)
    return link


def held(c, argv, call=None):
    """Run the command (or ``call``) while ``c.root / "held"`` is locked by another holder: a
    lock file this test opens and flocks itself, recording this pid, as a live run would."""
    import fcntl

    folder = c.root / "held"
    folder.mkdir(exist_ok=True)
    record = {"pid": os.getpid(), "host": socket.gethostname(), "started": "now",
              "command": "minimdm train held.yaml"}  # fmt: skip
    with open(folder / LOCK_NAME, "w") as f:
        f.write(json.dumps(record))
        f.flush()
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return main(argv) if call is None else call()


def foreign_lock(c):
    folder = c.root / "foreign"
    folder.mkdir(exist_ok=True)
    record = {"pid": 7, "host": "elsewhere", "started": "2026-01-01", "command": "minimdm rl x"}
    (folder / LOCK_NAME).write_text(json.dumps(record))
    with RunLock(folder):
        pass


def on_a_full_disk(call):
    """``call()`` while every write through minimdm.files fills the disk half-way."""
    from minimdm import files

    def full(f, data):
        f.write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    real, files._write = files._write, full
    try:
        return call()
    finally:
        files._write = real


def download_not_an_archive(c):
    from minimdm.motion import corpora

    src = c.root / "not_an_archive.txt"
    src.write_text("a web page, not an archive\n")
    home = c.root / "data_home"
    real_home, real = os.environ.get("MINIMDM_DATA"), dict(corpora.CORPORA)
    os.environ["MINIMDM_DATA"] = str(home)
    corpora.CORPORA["tiny"] = corpora.Corpus("tiny", "-", "CC0", "-", "", "tiny", src.as_uri())
    try:
        return corpora.download_corpus("tiny", progress=False)
    finally:
        corpora.CORPORA.clear()
        corpora.CORPORA.update(real)
        if real_home is None:
            os.environ.pop("MINIMDM_DATA", None)
        else:
            os.environ["MINIMDM_DATA"] = real_home
        assert not home.exists() or not list(home.iterdir()), list(home.iterdir())


# --- issue 27: no crash ----------------------------------------------------------------------
cli("cli/sample --frames 10^15", ("minimdm sample: error:", "--frames", "[1, 1000000]"),
    lambda c: ["sample", "--checkpoint", c.ckdir, "--frames", "1000000000000000",
               "--out", str(c.root / "x.npz")])  # fmt: skip
cli("cli/sample --samples 10^12", ("minimdm sample: error:", "--samples", "[1, 10000]"),
    lambda c: sample(c, "--samples", str(10**12)))  # fmt: skip
cli("cli/sample --frames x --samples beyond 10^6", ("minimdm sample: error:", "--frames times "
                                                    "--samples", "1000 x 5000"),
    lambda c: ["sample", "--checkpoint", c.ckdir, "--frames", "1000", "--samples", "5000",
               "--out", str(c.root / "x.npz")])  # fmt: skip
cli("cli/sample --seed 10^23", ("minimdm sample: error:", "--seed", "9223372036854775807"),
    lambda c: sample(c, "--seed", str(10**23)))  # fmt: skip
cli("cli/eval --states beyond the takes", ("minimdm eval: error:", "--states", "at most"),
    lambda c: ["eval", "--checkpoint", c.ckdir, "--states", "100000"])  # fmt: skip
cli("cli/train log_interval: 0", ("minimdm train: error:", "li.yaml", "log_interval", ">= 1"),
    lambda c: ["train", str(text_file("li.yaml", "log_interval: 0\n")(c)),
               "--out", str(c.root / "run")])  # fmt: skip
api("export_onnx/batch=0", InputError, ("batch", "[1, 65536]", "got 0"),
    lambda c: export_onnx(frame_graph(c.ck), batch=0))  # fmt: skip
api(
    "bvh//dev/zero",
    BVHError,
    ("/dev/zero", "not a regular file"),
    lambda c: load_bvh("/dev/zero"),
    skip=None if Path("/dev/zero").exists() else "no /dev/zero",
)
api(
    "bvh/a FIFO",
    BVHError,
    ("fifo.bvh", "not a regular file", "FIFO"),
    lambda c: load_bvh(fifo(c)),
    skip=None if hasattr(os, "mkfifo") else "no FIFOs",
)
api("bvh/a .bvh symlink to /dev/zero", BVHError, ("zero.bvh", "not a regular file"),
    lambda c: load_bvh(symlink(c, "zero.bvh", Path("/dev/zero"))),
    skip=None if Path("/dev/zero").exists() else "no /dev/zero")  # fmt: skip
api("bvh/a folder holding a FIFO", BVHError, ("fifo.bvh", "not a regular file"),
    lambda c: load_bvh(fifo(c, "fifo_folder").parent),
    skip=None if hasattr(os, "mkfifo") else "no FIFOs")  # fmt: skip
bvh_row("bvh/Frames: 2.9 million in a small file", BVHError,
        (":17:", "2900000 frames", "more than 1000000 frames"),
        sub("Frames: 3", "Frames: 2900000"))  # fmt: skip
bvh_row("bvh/Frames beyond the file", BVHError, (":17:", "expected 100000 frames",
                                                 "bytes cannot hold them"),
        sub("Frames: 3", "Frames: 100000"), fps=None)  # fmt: skip
bvh_row("bvh/frames x channels beyond the cap", BVHError, (":17:", "numbers, more than",
                                                           "split the take"),
        lambda t: t.replace("CHANNELS 3 Zrotation Xrotation Yrotation",
                            "CHANNELS 69" + " Xrotation" * 69)
        .replace("Frames: 3", "Frames: 999999"), fps=None)  # fmt: skip
bvh_row(
    "bvh/joints nested too deep",
    BVHError,
    ("nested at most 256 deep",),
    lambda t: t.replace(
        "  JOINT Chest\n",
        "".join(f"JOINT J{i} {{ OFFSET 0 1 0\n" for i in range(300)) + "  JOINT Chest\n",
    ),
)


def fifo(c, folder: str = "") -> Path:
    where = c.root / folder if folder else c.root
    where.mkdir(exist_ok=True)
    path = where / "fifo.bvh"
    if not path.exists():
        os.mkfifo(path)
    return path


# --- issue 27: no silent garbage -------------------------------------------------------------
def fast(c):
    """The ctx checkpoint's fast frame (exported once: a second or two)."""
    if "fast" not in c.cache:
        c.cache["fast"] = FastFrame(export_onnx(frame_graph(c.ck)))
    return c.cache["fast"]


def other_checkpoint(c):
    """A checkpoint like ctx's with other weights."""
    if "other" not in c.cache:
        torch.manual_seed(1)
        model = MLPDenoiser(DenoiserConfig(D, D, width=16, depth=2, time_dim=8))
        save_checkpoint(c.root / "other_ckpt", model, c.ck.metadata)
        c.cache["other"] = load_checkpoint(c.root / "other_ckpt")
    return c.cache["other"]


api("fast/state 1e30", InputError, ("state", "±10000", "1e+30"),
    lambda c: fast(c)(torch.full((1, D), 1e30), gen()))  # fmt: skip
api(
    "fast/noise 1e30",
    InputError,
    ("noise", "±10000", "1e+30"),
    lambda c: fast(c)(torch.zeros(1, D), noise=torch.full((1, sum(fast(c).noise_widths)), 1e30)),
)
api("fast/a string state", InputTypeError, ("state", "tensor", "str"),
    lambda c: fast(c)("abc", gen()))  # fmt: skip
api("rollout/fast graph exported from another checkpoint", InputError,
    ("fast", "another model", "other_ckpt", "weights"),
    lambda c: R(other_checkpoint(c), c.x0, 2, fast=fast(c)))  # fmt: skip
api("RLConfig/num_envs=2.7", InputTypeError, ("num_envs", "integer", "2.7"),
    lambda c: RLConfig(num_envs=2.7))  # fmt: skip
api("RLConfig/gamma=nan", InputError, ("gamma", "finite"), lambda c: RLConfig(gamma=NAN))
api("SteeringVecEnv/action_penalty=nan", InputError, ("action_penalty", "finite", "nan"),
    lambda c: steering_env(c, action_penalty=NAN))  # fmt: skip
api("SteeringVecEnv/num_envs=2.7", InputTypeError, ("num_envs", "integer", "2.7"),
    lambda c: steering_env(c, num_envs=2.7))  # fmt: skip
api("SteeringVecEnv/NaN start frames", InputError, ("starts", "finite"),
    lambda c: steering_env(c, starts=torch.full((3, D), NAN)))  # fmt: skip
cli("cli/rl base: camdm", ("minimdm rl: error:", "base (", "rl_camdm.yaml", "kind 'camdm'"),
    lambda c: ["rl", str(text_file("rl_camdm.yaml", "base: camdm\n")(c)),
               "--out", str(c.root / "run")], skip=None if (SHIPPED / "camdm").exists()
    else "no shipped camdm checkpoint")  # fmt: skip
api("config/eval_windows: 0", ValueError, ("ew.yaml", "eval_windows", ">= 1"),
    lambda c: load_config(text_file("ew.yaml", "eval_windows: 0\n")(c), TrainConfig))  # fmt: skip
NO_CAMDM = None if (SHIPPED / "camdm").exists() else "no shipped camdm checkpoint"


def camdm(c, part: str):
    """The shipped CAMDM's controller, or its fast planner (exported once)."""
    from minimdm.camdm.controller import CAMDMController

    if "camdm" not in c.cache:
        c.cache["camdm"] = CAMDMController(SHIPPED / "camdm")
    if part == "fast" and "camdm_fast" not in c.cache:
        c.cache["camdm_fast"] = FastFrame(export_onnx(frame_graph(c.cache["camdm"].checkpoint)))
    return c.cache["camdm" if part == "controller" else "camdm_fast"]


def camdm_plan(c, trajectory=None, style=0):
    ctl = camdm(c, "controller")
    L = ctl.layout
    traj = torch.zeros(1, L.future, 4) if trajectory is None else trajectory
    return ctl.plan(torch.zeros(1, L.past, L.dim), style, traj, gen())


def camdm_fast(c, style: int):
    f, L = camdm(c, "fast"), camdm(c, "controller").layout
    return f(torch.zeros(1, L.past, L.dim), gen(), style=torch.tensor([style]),
             trajectory=torch.zeros(1, L.future, 4), gamma=torch.ones(1))  # fmt: skip


api("CAMDMController.plan/trajectory 1e30", InputError, ("trajectory", "±10000", "1e+30"),
    lambda c: camdm_plan(c, torch.full((1, 45, 4), 1e30)), skip=NO_CAMDM)  # fmt: skip
api("CAMDMController.plan/style=-1", InputError, ("style", "-1"),
    lambda c: camdm_plan(c, style=-1), skip=NO_CAMDM)  # fmt: skip
api("fast/CAMDM style=-1", InputError, ("style", "[0, 14]", "-1"),
    lambda c: camdm_fast(c, -1), skip=NO_CAMDM)  # fmt: skip
api("fast/CAMDM style=15", InputError, ("style", "[0, 14]", "15"),
    lambda c: camdm_fast(c, 15), skip=NO_CAMDM)  # fmt: skip
api("CAMDMController/planner of another model", InputError, ("planner", "another model", "amdm"),
    lambda c: camdm_other_planner(c), skip=NO_CAMDM)  # fmt: skip


def camdm_other_planner(c):
    from minimdm.camdm.controller import CAMDMController

    f = camdm(c, "fast")
    meta = {**f.metadata, "checkpoint": {**f.metadata["checkpoint"], "name": "amdm",
                                         "fingerprint": "0123456789abcdef"}}  # fmt: skip

    class Renamed:  # the same graph, claiming another source
        metadata = meta

        def __call__(self, *a, **k):
            return f(*a, **k)

    return CAMDMController(camdm(c, "controller").checkpoint, planner=Renamed())


def steering_env(c, starts=None, **kw):
    from minimdm.rl.env import ResidualSteerer, SteeringVecEnv
    from minimdm.rl.residual import ResidualSchedule
    from minimdm.rl.tasks import make_task

    cm = Sampler.load(c.ck)
    steer = ResidualSteerer(cm, ResidualSchedule.top(T, 2, tied=True), "all")
    starts = encode(c.clip) if starts is None else starts
    return SteeringVecEnv(cm, steer, make_task("target"), starts, **{"num_envs": 2, **kw})


# --- issue 27: one line, not a traceback -----------------------------------------------------
def aamdm_cli(id: str, words: tuple[str, ...], argv) -> None:
    """A row that runs ``python -m minimdm.aamdm ARGV``: exit 2 and one error line."""
    from minimdm.cli import aamdm_main

    ROWS.append(Row(id, lambda c: aamdm_main(argv(c)), "exit 2",
                    ("python -m minimdm.aamdm train: error:", *words)))  # fmt: skip


BINARY = bytes(range(128, 256)) * 4  # not UTF-8
aamdm_cli(
    "aamdm/missing config",
    ("nope.yaml", "does not exist"),
    lambda c: ["train", str(c.root / "nope.yaml"), "--out", str(c.root / "run")],
)
aamdm_cli("aamdm/unknown key", ("typo.yaml", "unknown config keys", "['widht']"),
          lambda c: ["train", str(text_file("typo.yaml", "widht: 5\n")(c)),
                     "--out", str(c.root / "run")])  # fmt: skip
aamdm_cli("aamdm/YAML error", ("bad.yaml:2", "not valid YAML"),
          lambda c: ["train", str(text_file("bad.yaml", BAD_YAML)(c)),
                     "--out", str(c.root / "run")])  # fmt: skip
aamdm_cli(
    "aamdm/binary YAML",
    ("binary.yaml", "not a text file"),
    lambda c: ["train", str(binary_file(c, "binary.yaml")), "--out", str(c.root / "run")],
)
aamdm_cli("aamdm/unwritable --out", ("--out", "cannot write"),
          lambda c: ["train", "configs/aamdm.yaml", "--out", "/proc/minimdm/run"])  # fmt: skip
aamdm_cli("aamdm/--out a file", ("--out", "is a file"),
          lambda c: ["train", "configs/aamdm.yaml", "--out", str(c.root / "a_file")])  # fmt: skip
aamdm_cli("aamdm/--threads 0", ("--threads", ">= 1"),
          lambda c: ["train", "configs/aamdm.yaml", "--threads", "0"])  # fmt: skip
aamdm_cli("aamdm/--out checkpoints/aamdm", SHIP,
          lambda c: ["train", "configs/aamdm.yaml", "--out", str(SHIPPED / "aamdm")])  # fmt: skip
aamdm_cli("aamdm/ae_steps: 0", ("zero.yaml", "ae_steps", ">= 1"),
          lambda c: ["train", str(text_file("zero.yaml", "ae_steps: 0\n")(c)),
                     "--out", str(c.root / "run")])  # fmt: skip
cli(
    "cli/train --set width=[1",
    ("minimdm train: error:", "--set 'width=[1'", "not valid YAML"),
    lambda c: ["train", str(OK_YAML(c)), "--out", str(c.root / "run"), "--set", "width=[1"],
)
cli(
    "cli/train binary YAML",
    ("minimdm train: error:", "binary.yaml", "not a text file"),
    lambda c: ["train", str(binary_file(c, "binary.yaml")), "--out", str(c.root / "run")],
)
cli("cli/train unknown key names the file", ("minimdm train: error:", "typo.yaml", "['widht']"),
    lambda c: ["train", str(text_file("typo.yaml", "widht: 5\n")(c)),
               "--out", str(c.root / "run")])  # fmt: skip
cli("cli/train --out unwritable", ("minimdm train: error:", "--out", "/proc/minimdm/run"),
    lambda c: ["train", str(OK_YAML(c)), "--out", "/proc/minimdm/run"])  # fmt: skip
cli("cli/camdm train --threads 0", ("minimdm camdm train: error:", "--threads", ">= 1"),
    lambda c: ["camdm", "train", "configs/camdm.yaml", "--threads", "0"])  # fmt: skip
cli("cli/rl --set num_envs=2.7", ("minimdm rl: error:", "--set", "num_envs", "2.7"),
    lambda c: ["rl", "configs/rl_target.yaml", "--set", "num_envs=2.7",
               "--out", str(c.root / "run")])  # fmt: skip
cli("cli/rl --set action_penalty=nan", ("minimdm rl: error:", "action_penalty", "finite"),
    lambda c: ["rl", "configs/rl_target.yaml", "--set", "action_penalty=.nan",
               "--out", str(c.root / "run")])  # fmt: skip
cli("cli/camdm classifier --set steps=0", ("minimdm camdm classifier: error:", "steps", ">= 1"),
    lambda c: ["camdm", "classifier", "configs/camdm_classifier.yaml", "--set", "steps=0",
               "--out", str(c.root / "run")])  # fmt: skip


def binary_file(c, name: str) -> Path:
    path = c.root / name
    path.write_bytes(BINARY)
    return path


# --------------------------------------------------------------------------------------------
# The test


@pytest.mark.parametrize("r", ROWS, ids=[r.id for r in ROWS])
def test_bad_input_is_named(r: Row, ctx, capsys):
    if r.skip:
        pytest.skip(r.skip)
    capsys.readouterr()
    if r.error == "exit 2":
        try:
            code = r.run(ctx)
        except SystemExit as e:  # argparse
            code = e.code
        err = capsys.readouterr().err
        assert code == 2, err
        assert "Traceback" not in err
        message = err.strip().splitlines()[-1]  # argparse prints its usage above the error
        assert message.startswith(("minimdm", "python -m minimdm.aamdm")), err
        assert len(err.strip().splitlines()) == 1 or err.lstrip().startswith("usage:"), err
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pytest.raises(r.error) as info:
                r.run(ctx)
        message = str(info.value)
    missing = [w for w in r.words if w not in message]
    assert not missing, f"{missing} not in: {message}"


def test_the_table_is_broad():
    """The table covers the API, BVH, checkpoints, configs and the CLI with distinct inputs."""
    ids = [r.id for r in ROWS]
    assert len(ids) == len(set(ids))
    kinds = {i.split("/")[0] for i in ids}
    assert {"rollout", "inpaint", "inbetween", "beam_search", "bvh", "checkpoint", "cli"} <= kinds
    assert len(ROWS) >= 150


# --------------------------------------------------------------------------------------------
# Inputs that must work, and what the errors must not cost


def test_good_input_still_samples_bit_for_bit(ctx):
    """The checks change nothing for valid input: a clip, its frames plus its start pose and
    the same frames with no pose give the same features, bit for bit, seed for seed."""
    a = rollout(ctx.ck, ctx.clip, 3, 2, generator=gen(1))
    x = encode(ctx.clip)[-1]
    b = rollout(ctx.ck, x, 3, 2, generator=gen(1), start_pose=start_pose_of(ctx.clip, 11))
    c = rollout(ctx.ck, x.numpy(), 3, 2, generator=gen(1))
    assert torch.equal(a.features, b.features) and torch.equal(a.features, c.features)
    assert torch.equal(a.positions, b.positions)
    # the same topology with other bone lengths (another actor) is the same skeleton
    sk = ctx.clip.skeleton
    longer = Skeleton(sk.names, sk.parents, sk.offsets * 1.1, sk.foot_joints, sk.lateral_axis)
    pose = start_pose_of(ctx.clip, 11)
    pose.skeleton = longer
    rollout(ctx.ck, x, 2, start_pose=pose, generator=gen(1))


def test_bvh_with_a_byte_order_mark_or_latin1_names_loads(tmp_path):
    (tmp_path / "bom.bvh").write_bytes(b"\xef\xbb\xbf" + BVH.encode())
    assert load_bvh(tmp_path / "bom.bvh").skeleton.names == ["Hips", "Chest"]
    (tmp_path / "latin1.bvh").write_bytes(BVH.replace("Chest", "Épaule").encode("latin-1"))
    assert load_bvh(tmp_path / "latin1.bvh").skeleton.names == ["Hips", "Épaule"]


def test_a_torn_last_log_line_is_skipped_with_a_warning(tmp_path):
    log = tmp_path / "log.jsonl"
    log.write_text('{"step": 1, "loss": 0.5}\n{"step": 2, "loss": 0.4}\n{"step": 3, "lo')
    with pytest.warns(UserWarning, match=r"log\.jsonl:3: skipping a torn last log line"):
        records = read_log(log)
    assert [r["step"] for _, r in records] == [1, 2]


def test_training_resumes_past_a_torn_log_line(tmp_path):
    cfg = TrainConfig(width=16, depth=2, time_dim=8, T=2, batch_size=4, total_steps=2, rollout=1,
                      teacher_steps=1, ramp_steps=1, eval_interval=0, ckpt_interval=0,
                      log_interval=1)  # fmt: skip
    feats = [torch.randn(12, 7, generator=gen(0))]
    train_amdm(cfg, tmp_path, feats, progress=False)
    with open(tmp_path / "log.jsonl", "a") as f:
        f.write('{"step": 3, "lo')  # the process died while writing this line
    cfg = TrainConfig(**{**cfg.__dict__, "total_steps": 3})
    with pytest.warns(UserWarning, match="log.jsonl"):
        result = train_amdm(cfg, tmp_path, feats, progress=False)
    assert result.steps == 3
    steps = [json.loads(line)["step"] for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert steps[-1] == 3


def test_temp_files_of_dead_writers_are_removed(tmp_path, ctx):
    dead = tmp_path / ".model.safetensors.tmp999999999"  # no such process
    live = tmp_path / f".model.safetensors.tmp{1}"  # init, always alive
    other = tmp_path / ".other.safetensors.tmp999999999"  # another file's temp: not ours
    for f in (dead, live, other):
        f.write_bytes(b"partial")
    save_checkpoint(tmp_path, ctx.ck.model, {})
    assert not dead.exists() and live.exists() and other.exists()


def test_sample_checks_its_output_before_sampling(ctx, monkeypatch, capsys):
    """A bad --out fails before the model is even loaded: no work is lost."""
    import minimdm.checkpoint

    def no_loading(*a, **k):
        raise AssertionError("the checkpoint was loaded before --out was checked")

    monkeypatch.setattr(minimdm.checkpoint, "load_checkpoint", no_loading)
    assert main(sample(ctx, out="folder.npz")) == 2
    assert "--out" in capsys.readouterr().err


def test_debug_shows_the_traceback(ctx):
    with pytest.raises(InputError, match="--device"):
        main(sample(ctx, "--device", "banana", "--debug"))


def test_a_bug_is_not_hidden(ctx, monkeypatch):
    """Only user errors become one line; anything else keeps its traceback."""
    import minimdm.checkpoint

    def bug(*a, **k):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(minimdm.checkpoint, "load_checkpoint", bug)
    with pytest.raises(ZeroDivisionError):
        main(sample(ctx))


def test_a_good_sample_still_works(ctx, tmp_path):
    out = tmp_path / "sub" / "m.npz"
    assert main(sample(ctx, "--quiet", "--start", "sway:4", out=str(out))) == 0
    assert np.load(out)["positions"].shape == (2, J, 3)


def test_yaml_rows_are_real_yaml_errors():
    with pytest.raises(yaml.YAMLError):
        yaml.safe_load(BAD_YAML)
    assert StartPose(torch.zeros(2), torch.zeros(())).skeleton is None
