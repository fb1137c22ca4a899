"""Steering policies as checkpoints: the actor network, its metadata, and loading them back.

A trained policy is stored like every minimdm checkpoint (safetensors + JSON, never pickled):
the actor of stable-baselines3's PPO copied into :class:`PolicyNet`, plus what is needed to use
it again -- the task and its options, the steering (residual schedule or latent scale), and the
identity of the frozen base model it was trained on (name, kind and a fingerprint of its
weights). :func:`load_steering` rebuilds everything and refuses a policy whose base model or
task is not the one asked for, naming both.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from minimdm.amdm.sampling import Sampler
from minimdm.checkpoint import (
    Checkpoint,
    CheckpointMismatchError,
    fingerprint,
    load_checkpoint,
)

from .env import Steerer, make_steerer
from .nets import PolicyNet
from .tasks import Task, make_task

__all__ = [
    "PolicyNet",
    "Steering",
    "fingerprint",
    "load_steering",
    "resolve_checkpoint",
]


def resolve_checkpoint(name: str | os.PathLike | Checkpoint) -> Checkpoint:
    """A loaded checkpoint from a shipped name (``"amdm"``), a path, or itself."""
    if isinstance(name, Checkpoint):
        return name
    from minimdm import CHECKPOINT_DIR, pretrained

    p = Path(name)
    if (CHECKPOINT_DIR / str(name) / "model.safetensors").exists() and not p.exists():
        return pretrained(str(name))
    return load_checkpoint(p)


def base_identity(ckpt: Checkpoint, name: str) -> dict[str, Any]:
    """What a policy records about its base model."""
    return {"name": str(name), "kind": ckpt.kind, "fingerprint": fingerprint(ckpt.model)}


@dataclass
class Steering:
    """A trained policy with the base model, steerer and task it was trained with."""

    policy: PolicyNet
    cm: Sampler
    steerer: Steerer
    task: Task
    checkpoint: Checkpoint
    """The policy's checkpoint (its metadata: config, command, training log summary)."""
    observe: str = "frame"
    """What the policy sees besides the task (:class:`~minimdm.rl.env.SteeringVecEnv`)."""


def load_steering(
    policy: str | os.PathLike | Checkpoint,
    base: str | os.PathLike | Checkpoint | None = None,
    task: str | None = None,
) -> Steering:
    """Load a policy checkpoint (a shipped name such as ``"rl_target"`` or a path) with its
    base model, steerer and task.

    Args:
        policy: the policy checkpoint.
        base: the base model to steer (default: the one the policy names). A different one --
            other weights, or another kind -- raises :class:`CheckpointMismatchError` naming
            both.
        task: the task the caller wants (e.g. ``"joystick"``); a policy trained for another
            task raises, naming both.
    """
    pc = resolve_checkpoint(policy)
    if pc.kind != "policy":
        raise ValueError(f"{pc.paths.weights} is a {pc.kind!r} checkpoint, not a steering policy")
    meta = pc.metadata
    stored = meta["base"]
    trained_task = meta["task"]["name"]
    if task is not None and task != trained_task:
        raise CheckpointMismatchError(
            f"policy {pc.paths.weights} was trained for the task {trained_task!r}, not {task!r}"
        )
    bc = resolve_checkpoint(base if base is not None else stored["name"])
    have = base_identity(bc, str(base if base is not None else stored["name"]))
    if (have["kind"], have["fingerprint"]) != (stored["kind"], stored["fingerprint"]):
        raise CheckpointMismatchError(
            f"policy {pc.paths.weights} was trained on the base model {stored['name']!r} "
            f"({stored['kind']}, weights {stored['fingerprint']}), but the base model given is "
            f"{have['name']!r} ({have['kind']}, weights {have['fingerprint']}, "
            f"{bc.paths.weights})"
        )
    cm = Sampler.load(bc, steps=meta["steering"].get("steps"))
    steerer = make_steerer(cm, meta["steering"])
    opts = {k: v for k, v in meta["task"].items() if k != "name"}
    for k, v in list(opts.items()):
        if isinstance(v, list):
            opts[k] = tuple(v)
    observe = meta.get("config", {}).get("observe", "frame")
    return Steering(pc.model, cm, steerer, make_task(trained_task, **opts), pc, observe)
