"""Running a trained policy: a steered motion, frame after frame on the one rollout loop.

:func:`steer` puts N characters in a :class:`~minimdm.rl.env.SteeringVecEnv` (no automatic
restarts), lets the caller set the goals (fixed targets, joystick commands, a path), then runs
:func:`minimdm.amdm.sampling.autoregress` with a step that asks the policy for actions and the
environment for the next frame. It returns the motion decoded to joint positions with the
task's rewards and measurements per frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from minimdm.amdm.sampling import autoregress
from minimdm.motion.features import StartPose, decode

from .env import SteeringVecEnv
from .policy import Steering

__all__ = ["SteeredMotion", "steer", "summary"]


@dataclass
class SteeredMotion:
    """N steered characters over F frames (frame 0, the start, excluded)."""

    features: Tensor
    """(N, F, D) frames in feature units."""
    positions: Tensor
    """(N, F, J, 3) global joint positions, metres, z up."""
    root_xy: Tensor
    """(N, F, 2) root ground positions (the environment's integration of the frames)."""
    heading: Tensor
    """(N, F) root headings, radians."""
    reward: Tensor
    """(N, F) the task's reward per frame."""
    info: dict[str, Tensor] = field(default_factory=dict)
    """(N, F) per-frame task measurements (``distance``, ``hit``, ``heading_error``...)."""
    start: Tensor | None = None
    """(N, D) the start frames, feature units."""
    goals: dict[str, Any] = field(default_factory=dict)
    """The task's goals as set before the run (targets, commands, paths)."""


def steer(
    steering: Steering,
    n_frames: int,
    num_envs: int = 1,
    starts: Tensor | None = None,
    setup: Callable[[SteeringVecEnv], None] | None = None,
    seed: int = 0,
    deterministic: bool = True,
    zero_policy: bool = False,
    progress: bool = False,
    controller: Callable[[SteeringVecEnv], Tensor] | None = None,
) -> SteeredMotion:
    """Roll ``num_envs`` characters out for ``n_frames`` frames under a trained policy.

    Args:
        steering: from :func:`~minimdm.rl.policy.load_steering`.
        n_frames: frames to generate (>= 1).
        num_envs: characters, stepped as one batch.
        starts: (P, D) start frames in feature units; character i starts from row i % P. Default:
            random frames of the base model's training takes (the environment's pool).
        setup: ``setup(env)`` after the reset, to put goals in place, e.g.
            ``lambda env: env.task.set_targets(...)``; the task's own random goals otherwise.
        seed: seeds the starts, goals and the model's noise.
        deterministic: act with the policy's mean (True) or sample from its Gaussian.
        zero_policy: act with zero residuals (the base model unsteered) -- a baseline.
        progress: tqdm bar over frames.
        controller: ``controller(env) -> actions (N, A)`` acts instead of the policy, e.g. a
            hand-written controller on the same actions -- a baseline.
    """
    from minimdm.rl.train import corpus_starts

    cm, pol = steering.cm, steering.policy
    pool = starts if starts is not None else corpus_starts(_base_of(steering), "train")
    env = SteeringVecEnv(
        cm, steering.steerer, steering.task, pool, num_envs, seed, observe=steering.observe
    )
    env.reset(seed=seed)
    if starts is not None:
        rows = torch.arange(num_envs) % len(starts)
        env.x = cm.normalize(torch.as_tensor(starts, dtype=torch.float32)[rows].to(cm.device))
        env.task.reset(torch.arange(num_envs), env.ch)
    if setup is not None:
        setup(env)
    goals = {k: v.clone() for k, v in vars(env.task).items() if isinstance(v, Tensor)}
    start = cm.denormalize(env.x).float().cpu()
    gen = torch.Generator().manual_seed(seed + 1)
    rec: dict[str, list[Tensor]] = {"reward": [], "xy": [], "heading": []}

    def step(f: int, x_prev: Tensor) -> Tensor:
        obs = torch.as_tensor(env._obs())
        if zero_policy:
            a = torch.zeros(num_envs, env.single_action_space.shape[0])
        elif controller is not None:
            a = controller(env).float().clamp(-1.0, 1.0)
        else:
            a = pol.act(obs, deterministic, gen)
        x, prev = env.advance(a)
        reward, _, info = env.task.step(env.ch, prev)
        rec["reward"].append(reward.clone())
        rec["xy"].append(env.ch.xy.clone())
        rec["heading"].append(env.ch.heading.clone())
        for k, v in info.items():
            rec.setdefault(k, []).append(v.clone())
        return x

    normalized = autoregress(step, env.x, n_frames, desc="steering", progress=progress)
    feats = cm.denormalize(normalized)
    positions = decode(feats.double(), StartPose.broadcast(None, num_envs)).float()
    stack = {k: torch.stack(v, dim=1) for k, v in rec.items()}
    return SteeredMotion(
        features=feats,
        positions=positions,
        root_xy=stack.pop("xy"),
        heading=stack.pop("heading"),
        reward=stack.pop("reward"),
        info=stack,
        start=start,
        goals=goals,
    )


def _base_of(steering: Steering):
    from .policy import resolve_checkpoint

    return resolve_checkpoint(steering.checkpoint.metadata["base"]["name"])


def summary(m: SteeredMotion) -> dict[str, float]:
    """Mean reward per frame and the task's measurements averaged over characters and frames."""
    out = {"reward_mean": float(m.reward.mean())}
    for k, v in m.info.items():
        out[k] = float(v.float().abs().mean()) if k.endswith("error") else float(v.float().mean())
    return out
