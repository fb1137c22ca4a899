"""Training a steering policy with stable-baselines3's PPO (A-MDM §5.1, eq. 6).

PPO itself is SB3's; this module only connects it to the batched environment:

* :class:`SB3VecEnv` adapts :class:`~minimdm.rl.env.SteeringVecEnv` to SB3's ``VecEnv``: SB3
  sees N environments, the base model still makes one batched call per step;
* :class:`RLConfig` is the run (``configs/rl_*.yaml``);
* :func:`train_policy` runs PPO with a tqdm bar, writes the learning curve as JSON lines
  (``log.jsonl``: environment steps, mean reward per step, mean episode return...), then
  stores the actor as a minimdm checkpoint (safetensors + JSON; SB3's pickled zip is never
  written).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from minimdm.amdm.sampling import Sampler
from minimdm.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from minimdm.config import load_config as _load_config
from minimdm.files import RunLock, atomic_write
from minimdm.motion.features import encode
from minimdm.utils import num_threads as threads
from minimdm.validate import InputError, check_choice, check_int, check_number, check_output_dir

from .env import OBSERVATIONS, LatentSteerer, ResidualSteerer, Steerer, SteeringVecEnv
from .policy import PolicyNet, base_identity, resolve_checkpoint
from .residual import ResidualSchedule
from .tasks import make_task

__all__ = [
    "RLConfig",
    "load_config",
    "SB3VecEnv",
    "corpus_starts",
    "build_env",
    "train_policy",
    "RLResult",
]


@dataclass
class RLConfig:
    """One policy training run. Every field has the value of the book's configs as default."""

    task: str = "target"
    """``target``, ``joystick`` or ``path`` (:mod:`minimdm.rl.tasks`)."""
    task_options: dict = field(default_factory=dict)
    """Options of the task's dataclass, e.g. ``{max_frames: 300}``."""
    base: str = "amdm"
    """The frozen base model: a shipped checkpoint name or a path (an A-MDM or an MVAE)."""
    steps: int | None = None
    """A-MDM: denoising steps per frame (None: all T, DDPM; fewer: DDIM on its grid of levels,
    which ``levels`` must then be on)."""
    levels: list[int] | None = None
    """A-MDM: the 0-based levels whose step output gets a residual (None: the ``n_levels``
    noisiest)."""
    n_levels: int = 10
    """A-MDM: how many of the noisiest levels get a residual when ``levels`` is None."""
    anneal: str = "linear"
    """A-MDM: the shape of :math:`w^t` (``linear``, ``cosine``, ``none``)."""
    residual_scale: float = 1.0
    """A-MDM: :math:`w^t` at the noisiest perturbed level, in normalized feature units."""
    features: str = "all"
    """A-MDM: residuals on ``all`` features, the ``root`` velocity and yaw rate, or the
    ``forward`` velocity and yaw rate (see :func:`~minimdm.rl.residual.feature_indices`)."""
    tied: bool = False
    """A-MDM: one residual for every perturbed step (True) or one per step (the paper)."""
    latent_scale: float = 2.0
    """MVAE: the latent is ``latent_scale`` times the action."""
    action_penalty: float = 0.0
    """Reward minus this times the mean squared action (stay close to the base model)."""
    motion_penalty: float = 0.0
    """Reward minus this per cm of the frame's bone length error plus foot sliding (stay on
    the data; see :class:`~minimdm.rl.env.SteeringVecEnv`)."""
    max_turn_rate: float | None = None
    """End an episode (terminated: no more reward) when the character spins: its yaw rate,
    averaged over about half a second, exceeds this many degrees per second (see
    :class:`~minimdm.rl.env.SteeringVecEnv`). None: never."""
    max_yaw_rate: float | None = None
    """A-MDM: the residual's turn governor, degrees per second (see
    :class:`~minimdm.rl.env.ResidualSteerer`): the yaw residual fades out as the character
    turns this fast in its direction. None: off."""
    observe: str = "frame"
    """What the policy sees besides the task: the whole current ``frame`` or only its ``root``
    velocity and yaw rate (see :class:`~minimdm.rl.env.SteeringVecEnv`)."""
    num_envs: int = 64
    """Characters stepped together (one batched model call)."""
    total_steps: int = 1_000_000
    """Environment steps (frames summed over the characters)."""
    n_steps: int = 32
    """PPO: steps per environment between updates (a rollout of num_envs * n_steps)."""
    batch_size: int = 512
    n_epochs: int = 5
    lr: float = 3.0e-4
    gamma: float = 0.97
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    target_kl: float | None = None
    """PPO: stop a rollout's epochs early when the approximate KL exceeds this (SB3's option)."""
    log_std_init: float = -0.7
    """Initial log std of the Gaussian policy (the official code fixes std 0.5: log 0.5 = -0.69)."""
    net_arch: list[int] = field(default_factory=lambda: [256, 256])
    start_split: str = "train"
    """Episodes start from frames of the base model's ``train`` takes (or ``test``)."""
    seed: int = 0
    config_file: str | None = None

    def __post_init__(self) -> None:
        for name in ("num_envs", "n_steps", "total_steps", "batch_size", "n_epochs", "n_levels"):
            check_int(name, getattr(self, name), low=1)  # 2.7 is refused, not rounded down
        for name in ("action_penalty", "motion_penalty"):
            check_number(name, getattr(self, name), low=0.0)
        for name in ("max_turn_rate", "max_yaw_rate"):
            if getattr(self, name) is not None:
                check_number(name, getattr(self, name), low=0.0, low_open=True)
        for name in ("residual_scale", "latent_scale", "clip_range", "max_grad_norm"):
            check_number(name, getattr(self, name), low=0.0, low_open=True)
        check_number("lr", self.lr, low=0.0, low_open=True)
        for name in ("gamma", "gae_lambda"):
            check_number(name, getattr(self, name), low=0.0, high=1.0)
        for name in ("ent_coef", "vf_coef"):
            check_number(name, getattr(self, name), low=0.0)
        check_number("log_std_init", self.log_std_init, low=-20.0, high=2.0)
        check_choice("observe", self.observe, OBSERVATIONS)
        if (self.num_envs * self.n_steps) % self.batch_size:
            raise ValueError(
                f"batch_size ({self.batch_size}) must divide num_envs * n_steps "
                f"({self.num_envs * self.n_steps})"
            )


def load_config(path: str | os.PathLike) -> RLConfig:
    """Read ``configs/rl_*.yaml`` into an :class:`RLConfig` (unknown keys are an error)."""
    return _load_config(path, RLConfig)


def corpus_starts(base: Checkpoint, split: str = "train") -> torch.Tensor:
    """(P, D) every frame of the base model's corpus takes (``split``), in feature units."""
    from minimdm.amdm.evaluation import checkpoint_clips

    return torch.cat([encode(c) for c in checkpoint_clips(base, split=split)])


def corpus_speed_range(frames: torch.Tensor, fps: float, q: float = 0.999) -> tuple[float, float]:
    """(0, the ``q`` quantile of the planar root speed) of frames (P, D) in feature units, m/s:
    the joystick speeds the corpus holds."""
    speed = frames[:, :2].norm(dim=1) * fps
    return (0.0, round(float(torch.quantile(speed, q)), 2))


STEERABLE = ("amdm", "mvae")
"""Kinds of base model a policy steers: A-MDM (residuals on its chain) and the MVAE (latent)."""


def load_base(config: RLConfig, base: Checkpoint | None = None) -> Checkpoint:
    """The config's base model (``base`` if given), refused unless it is of a kind a policy
    steers, naming the config key and file."""
    where = f" ({config.config_file})" if config.config_file else ""
    if base is None:
        try:
            base = resolve_checkpoint(config.base)
        except FileNotFoundError as e:
            raise FileNotFoundError(f"base{where}: {e}") from None
    if base.kind not in STEERABLE:
        raise InputError(
            f"base{where} must name an A-MDM or MVAE checkpoint (kinds {', '.join(STEERABLE)}) "
            f"to steer, but {config.base!r} ({base.paths.weights}) holds kind {base.kind!r}"
        )
    return base


def make_config_steerer(cm: Sampler, config: RLConfig) -> Steerer:
    if cm.is_diffusion:
        T = cm.schedule.T
        if config.levels is not None:
            sched = ResidualSchedule(
                T, tuple(config.levels), config.anneal, config.residual_scale, config.tied
            )
        else:
            sched = ResidualSchedule.top(
                T, config.n_levels, config.anneal, config.residual_scale, config.tied
            )
        return ResidualSteerer(cm, sched, config.features, config.max_yaw_rate)
    if config.max_yaw_rate is not None:
        raise ValueError("max_yaw_rate governs an A-MDM residual; an MVAE's latent has no yaw")
    return LatentSteerer(cm, config.latent_scale)


def build_env(
    config: RLConfig,
    base: Checkpoint | None = None,
    num_envs: int | None = None,
    seed: int | None = None,
) -> SteeringVecEnv:
    """The vector environment a config describes (its base model loaded if not given)."""
    base = load_base(config, base)
    cm = Sampler.load(base, steps=config.steps)
    opts = {k: tuple(v) if isinstance(v, list) else v for k, v in config.task_options.items()}
    starts = corpus_starts(base, config.start_split)
    if config.task == "joystick" and "corpus_speed" not in opts:
        opts["corpus_speed"] = corpus_speed_range(starts, cm.fps)
    task = make_task(config.task, **opts)
    return SteeringVecEnv(
        cm,
        make_config_steerer(cm, config),
        task,
        starts,
        num_envs or config.num_envs,
        config.seed if seed is None else seed,
        action_penalty=config.action_penalty,
        motion_penalty=config.motion_penalty,
        observe=config.observe,
        max_turn_rate=config.max_turn_rate,
    )


# ------------------------------------------------------------------------------------------
# stable-baselines3


def _sb3():
    from stable_baselines3.common.vec_env import VecEnv

    return VecEnv


LOGGED_KEYS = ("task_reward", "bone_cm", "slide_cm", "spun")
"""Per-frame values the environment reports (the task's reward before penalties, the motion's
quality, the share of frames that ended an episode in a spin), logged per rollout as means per
frame."""


class SB3VecEnv(_sb3()):
    """SB3's ``VecEnv`` over a :class:`SteeringVecEnv`: N environments, one model call a step.

    Finished episodes restart in the same step; SB3 gets the last observation as
    ``terminal_observation``, ``TimeLimit.truncated`` for episodes cut by the time limit (so
    that it bootstraps their value) and ``episode`` (return, length) as SB3's Monitor gives it.
    """

    def __init__(self, env: SteeringVecEnv) -> None:
        self.env = env
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)
        self._actions: np.ndarray | None = None
        self.finished: list[tuple[float, int]] = []
        """(return, length) of every episode finished since the last :meth:`drain`."""
        self.reward_sum, self.reward_count = 0.0, 0
        """The rewards (penalties included) since the last :meth:`drain` (SB3's buffer adds
        bootstrapped values to the rewards of time-limited steps, so it does not give them)."""
        self.quality_sums: dict[str, float] = {}
        """Sums of the frames' :data:`LOGGED_KEYS` since the last :meth:`drain`."""

    def reset(self):
        seed = self._seeds[0] if getattr(self, "_seeds", None) else None
        obs, _ = self.env.reset(seed=seed)
        if hasattr(self, "_reset_seeds"):
            self._reset_seeds()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.env.step(self._actions)
        self.reward_sum += float(reward.sum())
        self.reward_count += len(reward)
        for k in LOGGED_KEYS:
            if k in info:
                self.quality_sums[k] = self.quality_sums.get(k, 0.0) + float(info[k].sum())
        done = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(done):
            r, n = float(info["episode_return"][i]), int(info["episode_length"][i])
            infos[i] = {
                "terminal_observation": info["final_obs"][i],
                "TimeLimit.truncated": bool(truncated[i] and not terminated[i]),
                "episode": {"r": r, "l": n, "t": 0.0},
            }
            self.finished.append((r, n))
        return obs, reward.astype(np.float32), done, infos

    def drain(self) -> tuple[float, list[tuple[float, int]], dict[str, float]]:
        """The mean reward per step, the finished episodes and the means per step of
        :data:`LOGGED_KEYS` (those measured) since the last call."""
        n = max(self.reward_count, 1)
        mean = self.reward_sum / n
        quality = {k: v / n for k, v in self.quality_sums.items()}
        out, self.finished = self.finished, []
        self.reward_sum, self.reward_count, self.quality_sums = 0.0, 0, {}
        return mean, out, quality

    def close(self) -> None:
        pass

    def get_attr(self, attr_name, indices=None):
        return [getattr(self.env, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name, value, indices=None):
        setattr(self.env, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        return [getattr(self.env, method_name)(*args, **kwargs)] * len(self._indices(indices))

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(self._indices(indices))

    def _indices(self, indices):
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else indices


def _callback(total: int, log_path: Path, progress: bool, adapter: SB3VecEnv, t0: float):
    from stable_baselines3.common.callbacks import BaseCallback

    class Curve(BaseCallback):
        """tqdm over environment steps; one JSON line per PPO rollout (the learning curve)."""

        def _on_training_start(self) -> None:
            self.bar = tqdm(
                total=total, disable=not progress, desc="PPO", unit="step", unit_scale=True
            )
            atomic_write(log_path, "")  # a fresh curve, then one appended line per rollout
            self.file = open(log_path, "a")
            self.rows: list[dict] = []

        def _on_step(self) -> bool:
            self.bar.update(adapter.num_envs)
            return True

        def _on_rollout_end(self) -> None:
            reward_mean, eps, quality = adapter.drain()
            logged = self.model.logger.name_to_value
            row = {
                "env_steps": int(self.num_timesteps),
                "seconds": round(time.time() - t0, 1),
                "reward_mean": reward_mean,
                "episodes": len(eps),
                "return_mean": float(np.mean([r for r, _ in eps])) if eps else None,
                "length_mean": float(np.mean([n for _, n in eps])) if eps else None,
                "std": float(self.model.policy.log_std.detach().exp().mean()),
                **quality,
            }
            for k in ("train/approx_kl", "train/value_loss", "train/explained_variance"):
                if k in logged:
                    row[k.split("/")[1]] = float(logged[k])
            self.rows.append(row)
            self.file.write(json.dumps(row) + "\n")
            self.file.flush()
            self.bar.set_postfix(reward=f"{row['reward_mean']:.3f}")

        def _on_training_end(self) -> None:
            self.bar.close()
            self.file.close()

    return Curve()


@dataclass
class RLResult:
    """What :func:`train_policy` returns."""

    checkpoint: Checkpoint
    """The stored policy (reloaded from disk)."""
    history: list[dict]
    """The learning curve, one row per PPO rollout (as in ``log.jsonl``)."""
    seconds: float
    env_steps: int
    model: Any = None
    """SB3's PPO object, in memory only (never saved)."""


def train_policy(
    config: RLConfig,
    out: str | os.PathLike,
    progress: bool = True,
    num_threads: int = 1,
    metadata: dict | None = None,
    base: Checkpoint | None = None,
) -> RLResult:
    """Train a steering policy with SB3's PPO and store it in ``out`` (a checkpoint folder).

    The base model stays frozen. ``out/log.jsonl`` receives the learning curve, one line per
    PPO rollout; ``out/model.safetensors`` + ``model.json`` the actor and its metadata: the
    config, the task, the steering, the base model's identity, training time and steps.
    """
    out = check_output_dir("out", out)
    with RunLock(out, (metadata or {}).get("command")), threads(num_threads):
        return _train_policy(config, out, progress, metadata, base)


def _train_policy(
    config: RLConfig,
    out: Path,
    progress: bool,
    metadata: dict | None,
    base: Checkpoint | None,
) -> RLResult:
    from stable_baselines3 import PPO

    torch.manual_seed(config.seed)
    base = load_base(config, base)
    env = build_env(config, base)
    adapter = SB3VecEnv(env)
    adapter.seed(config.seed)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = PPO(
        "MlpPolicy",
        adapter,
        learning_rate=config.lr,
        n_steps=config.n_steps,
        batch_size=config.batch_size,
        n_epochs=config.n_epochs,
        gamma=config.gamma,
        gae_lambda=config.gae_lambda,
        clip_range=config.clip_range,
        ent_coef=config.ent_coef,
        vf_coef=config.vf_coef,
        max_grad_norm=config.max_grad_norm,
        target_kl=config.target_kl,
        policy_kwargs={
            "net_arch": {"pi": list(config.net_arch), "vf": list(config.net_arch)},
            "log_std_init": config.log_std_init,
        },
        seed=config.seed,
        device="cpu",
        verbose=0,
    )
    t0 = time.time()
    cb = _callback(config.total_steps, out / "log.jsonl", progress, adapter, t0)
    model.learn(total_timesteps=config.total_steps, callback=cb)
    seconds = time.time() - t0
    net = export_actor(model)
    last = cb.rows[-10:]
    meta = {
        **(metadata or {}),
        "config": asdict(config),
        "config_file": config.config_file,
        "task": env.task.to_dict(),
        "steering": env.steerer.to_dict(),
        "base": base_identity(base, config.base),
        "feature_layout": base.feature_layout,
        "skeleton": base.skeleton,
        "env_steps": int(model.num_timesteps),
        "train_seconds": round(seconds, 1),
        "final_reward_mean": float(np.mean([r["reward_mean"] for r in last])) if last else None,
    }
    save_checkpoint(out, net, meta)
    return RLResult(load_checkpoint(out), cb.rows, seconds, int(model.num_timesteps), model)


def export_actor(model) -> PolicyNet:
    """Copy the actor of an SB3 ``PPO("MlpPolicy")`` into a :class:`PolicyNet`."""
    pol = model.policy
    linears = [m for m in pol.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
    net = PolicyNet(
        linears[0].in_features, pol.action_net.out_features, tuple(l.out_features for l in linears)
    )
    body = [m for m in net.body if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        for mine, theirs in zip(body, linears, strict=True):
            mine.weight.copy_(theirs.weight)
            mine.bias.copy_(theirs.bias)
        net.head.weight.copy_(pol.action_net.weight)
        net.head.bias.copy_(pol.action_net.bias)
        net.log_std.copy_(pol.log_std)
    return net.eval()
