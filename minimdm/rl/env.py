"""The steering environments: N characters as one batch, stepped by one call of the frozen model.

:class:`SteeringVecEnv` is a gymnasium :class:`~gymnasium.vector.VectorEnv`. Its state is one
batched tensor of the characters' current frames (N, D), in the base model's normalized space,
and their root state (:class:`~minimdm.rl.tasks.Characters`). A step takes the policy's actions
(N, A) and asks the :class:`Steerer` for every character's next frame at once:

* :class:`ResidualSteerer` (A-MDM §5.2): the actions are residuals on K denoising steps, added
  by :func:`~minimdm.rl.residual.residual_hook` inside the one reverse chain (eq. 7);
* :class:`LatentSteerer` (MVAE, Ling et al. 2020): the action is the decoder's latent z.

The root is integrated from the new frame's velocity and yaw rate (as
:func:`minimdm.motion.features.decode_root` does), the task scores it, and finished episodes
restart at once from a random corpus frame (gymnasium's same-step autoreset: the last
observation is in ``infos["final_obs"]``). The observation is the current frame followed by the
task observation (or, with ``observe="root"``, only the frame's root velocity and yaw rate then
the task observation). :class:`SteeringEnv` is the single-character view that gymnasium's
environment checker and the chapter's live widget use.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from torch import Tensor

from minimdm.amdm.models import MVAE
from minimdm.amdm.sampling import Sampler
from minimdm.motion import metrics
from minimdm.motion.skeleton import rotate_about_z, wrap_angle
from minimdm.validate import check_frames, check_int, check_number

from .residual import ResidualSchedule, feature_indices, residual_hook
from .tasks import Characters, Task

__all__ = [
    "Steerer",
    "ResidualSteerer",
    "LatentSteerer",
    "make_steerer",
    "SteeringVecEnv",
    "SteeringEnv",
    "check_actions",
    "OBSERVATIONS",
]

OBSERVATIONS = ("frame", "root")
"""What a policy sees of the character besides its task: the whole current frame (the paper's
choice, D numbers) or only its root velocity and yaw rate (3 numbers)."""
TURN_FRAMES = 15
"""Frames of the exponential average of the yaw rate that ``max_turn_rate`` watches (half a
second at 30 fps)."""


def _non_finite_row(x: Tensor) -> int | None:
    """The first row of ``x`` (N, D) that holds NaN or Inf, or None when every value is finite."""
    if torch.isfinite(x).all():
        return None
    return (~torch.isfinite(x)).any(1).nonzero()[0].item()


def check_actions(actions: Any, n: int, dim: int) -> Tensor:
    """``actions`` as a float32 (n, dim) tensor; ``ValueError`` for another shape or NaN/Inf."""
    a = torch.as_tensor(np.asarray(actions), dtype=torch.float32)
    if a.shape != (n, dim):
        raise ValueError(f"actions must have shape ({n}, {dim}), got {tuple(a.shape)}")
    if (bad := _non_finite_row(a)) is not None:
        raise ValueError(f"actions must be finite, but environment {bad} holds NaN/Inf")
    return a


class Steerer:
    """How actions steer the base model: ``steerer(cond, actions, generator) -> next frame``."""

    action_dim: int
    kind: str

    def __call__(self, cond: Tensor, actions: Tensor, generator: torch.Generator) -> Tensor:
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        raise NotImplementedError


class ResidualSteerer(Steerer):
    """A-MDM residual steering (eq. 7): actions (N, K * F) in [-1, 1] are residuals on the
    ``features`` of the K steps of ``schedule``, weighted by :math:`w^t` (times its scale), in
    standard deviations of the normalized frame's features, whether the base model denoises
    the frame or its change from the previous one (then they are divided by the change's scale
    k on their way into the chain, :func:`~minimdm.rl.residual.residual_hook`'s ``units``).

    ``max_yaw_rate`` (degrees per second, None: off) is a turn governor on the yaw residual: a
    push that would turn the character faster fades out as the current frame's yaw rate
    approaches the limit L in the push's direction (linearly from 3/4 L to nothing at L and
    past it); pushes against the turn pass whole. A base model that denoises the change from
    the previous frame keeps a turn that was pushed past about 200 degrees per second going by
    itself, and then its own yaw residual hardly stops it (``benchmarks/rl_residual_gain.py
    --spin``); the governor keeps the residual from pushing it there. The model can still carry
    a turn past the limit by itself (a governor that also pushed back past the limit was tried
    and did worse: chapter 7). It is part of the steerer, so the policy, the baselines and the
    exported graph all run behind it.
    """

    kind = "residual"

    def __init__(
        self,
        cm: Sampler,
        schedule: ResidualSchedule,
        features: str = "all",
        max_yaw_rate: float | None = None,
    ):
        if not cm.is_diffusion:
            raise ValueError(
                f"residual steering needs an A-MDM denoiser, got {type(cm.net).__name__}"
            )
        if schedule.T != cm.schedule.T:
            raise ValueError(
                f"the residual schedule has T={schedule.T}, the model T={cm.schedule.T}"
            )
        self.cm, self.schedule, self.features = cm, schedule, features
        self.idx = feature_indices(cm.layout, features) if features != "all" else None
        self.per_step = len(self.idx) if self.idx is not None else cm.dim
        self.action_dim = schedule.n_residuals * self.per_step
        self.chain = cm.settings.levels(cm.schedule.T)  # the levels of a frame's chain
        k = cm.net.delta_k if cm.net.is_delta else None  # a delta model's scale of the change
        self.units = None if k is None else 1 / (k if self.idx is None else k[self.idx])
        self.max_yaw_rate = None
        if max_yaw_rate is not None:
            self.max_yaw_rate = check_number("max_yaw_rate", max_yaw_rate, low=0.0, low_open=True)
            if cm.layout is None or cm.normalizer is None:
                raise ValueError("max_yaw_rate needs a base model with a feature layout")
            col = cm.layout.yaw_rate.start
            if self.idx is not None and col not in self.idx:
                raise ValueError(f"max_yaw_rate needs a residual on the yaw rate ({features!r})")
            self._yaw_col = col
            self._yaw_at = torch.zeros(self.per_step)  # 1 where the residual is the yaw rate's
            self._yaw_at[col if self.idx is None else self.idx.index(col)] = 1.0

    def governed(self, cond: Tensor, actions: Tensor) -> Tensor:
        """``actions`` (N, A) with the yaw residual faded out near ``max_yaw_rate``, given the
        current frames ``cond`` (N, D) normalized (unchanged when the governor is off)."""
        if self.max_yaw_rate is None:
            return actions
        limit = math.radians(self.max_yaw_rate) / self.cm.fps  # radians per frame
        rate = self.cm.denormalize(cond)[:, self._yaw_col].to(actions.dtype)  # (N,)
        a = actions.unflatten(-1, (-1, self.per_step))  # (N, K or 1, F)
        at = self._yaw_at.to(a)
        yaw = (a * at).sum(-1)  # (N, K or 1)
        room = ((limit - torch.sign(yaw) * rate[:, None]) / (limit / 4)).clamp(0.0, 1.0)
        return (a + at * (yaw * (room - 1))[..., None]).flatten(-2)  # (N, A)

    def __call__(self, cond, actions, generator):
        actions = self.governed(cond, torch.as_tensor(actions))
        hook = residual_hook(self.schedule, actions, self.chain, self.idx, self.units)
        return self.cm.frame(cond, generator, hook=hook)

    def to_dict(self):
        spec = {
            "kind": self.kind,
            "schedule": self.schedule.to_dict(),
            "features": self.features,
            "steps": self.cm.settings.steps,
        }
        if self.max_yaw_rate is not None:  # policies trained without it load as before
            spec["max_yaw_rate"] = self.max_yaw_rate
        return spec


class LatentSteerer(Steerer):
    """MVAE latent steering (Ling et al. 2020): the action (N, Z) in [-1, 1], times ``scale``,
    is the latent z the decoder turns into the next frame."""

    kind = "latent"

    def __init__(self, cm: Sampler, scale: float = 2.0):
        if not isinstance(cm.net, MVAE):
            raise ValueError(f"latent steering needs an MVAE, got {type(cm.net).__name__}")
        self.cm, self.scale = cm, float(scale)
        self.action_dim = cm.net.config.latent_dim

    @torch.no_grad()
    def __call__(self, cond, actions, generator):
        return self.cm.net.decode(self.scale * actions.to(cond), cond)

    def to_dict(self):
        return {"kind": self.kind, "scale": self.scale}


def make_steerer(cm: Sampler, spec: dict[str, Any]) -> Steerer:
    """A steerer from :meth:`Steerer.to_dict`'s output (as stored in a policy checkpoint)."""
    kind = spec.get("kind")
    if kind == "residual":
        return ResidualSteerer(
            cm,
            ResidualSchedule.from_dict(spec["schedule"]),
            spec["features"],
            spec.get("max_yaw_rate"),
        )
    if kind == "latent":
        return LatentSteerer(cm, spec.get("scale", 2.0))
    raise ValueError(f"steering kind must be 'residual' or 'latent', got {kind!r}")


class _FrameQuality:
    """Bone length error and foot sliding of each character's newest frame, in cm.

    The same measures as :func:`minimdm.motion.metrics.bone_length_error` and
    :func:`~minimdm.motion.metrics.foot_sliding`, one frame at a time: the feet's world positions
    of the previous frame are kept per character. Foot contact heights come from the start frames
    (their 5 % quantile, as :func:`~minimdm.motion.metrics.foot_contact_offsets`).
    """

    def __init__(self, cm: Sampler, starts: Tensor, n: int) -> None:
        sk, lay = cm.skeleton, cm.layout
        self.parents = list(sk.parents)
        self.ref = metrics.skeleton_bone_lengths(sk.offsets, sk.parents).float()
        self.feet = list(sk.foot_indices)
        self.pos_sl, self.J = lay.joint_pos, lay.n_joints
        z = self._local(starts.float().cpu())[:, self.feet, 2]
        self.z0 = torch.quantile(z, 0.05, dim=0)
        self.prev = torch.zeros(n, len(self.feet), 2)

    def _local(self, feats: Tensor) -> Tensor:
        return feats[:, self.pos_sl].unflatten(-1, (self.J, 3))

    def _feet_world(self, p: Tensor, xy: Tensor, heading: Tensor) -> Tensor:
        return rotate_about_z(p[:, self.feet, :2], heading) + xy[:, None, :]

    def reset(self, idx: Tensor, feats: Tensor, xy: Tensor, heading: Tensor) -> None:
        self.prev[idx] = self._feet_world(self._local(feats), xy, heading)

    def __call__(self, feats: Tensor, xy: Tensor, heading: Tensor) -> tuple[Tensor, Tensor]:
        p = self._local(feats)
        bone = (metrics.bone_lengths(p, self.parents).float() - self.ref).abs().mean(1) * 100
        feet = self._feet_world(p, xy, heading)
        weight = metrics.contact_weight(p[:, self.feet, 2] - self.z0)
        slide = ((feet - self.prev).norm(dim=-1) * weight).mean(1) * 100
        self.prev = feet
        return bone, slide


class SteeringVecEnv(VectorEnv):
    """N characters driven by one batched model call per step (see the module docstring).

    Args:
        cm: the frozen base model.
        steerer: how actions steer it.
        task: the task (fresh: the env calls its ``setup``).
        starts: (P, D) the corpus frames episodes start from, in feature units.
        num_envs: N.
        seed: seeds the generator of starts, goals and the model's noise.
        action_penalty: subtracted from the reward times the mean squared action: the policy
            pays for every push away from what the base model would do by itself.
        motion_penalty: subtracted from the reward per cm of the new frame's bone length
            error plus foot sliding (the quality measures of A-MDM eq. 11 and §7, computed on
            the one frame): the policy pays for frames that leave the data. Needs the base
            model's skeleton (checkpoints carry it).
        observe: ``"frame"``: the policy sees the whole current frame (normalized), as in the
            paper; ``"root"``: only the frame's root velocity and yaw rate (normalized). With
            the whole frame, PPO within the book's budget mostly learned from the body's 255
            numbers and barely from the 4 to 10 that state the task (chapter 7 measures it).
        max_turn_rate: terminate an episode when the character spins: when its yaw rate,
            averaged over :data:`TURN_FRAMES` frames (an exponential average), exceeds this
            many degrees per second (None: never). A base model that denoises the change from
            the previous frame carries a pushed yaw rate on into the next frames; pushed too
            hard, it spins on the spot, faster than nearly every frame of the corpus turns (the
            99th percentile of their yaw rates is about 240 degrees per second). The frame's
            reward is still paid; the episode's later rewards are lost, which is meant to teach
            the policy to keep out (on the joystick it did not help: chapter 7).

    Observation: (N, D + task.obs_dim) float32, the current frame (normalized) then the task's;
    (N, 3 + task.obs_dim) with ``observe="root"``.
    Action: (N, A) float32 in [-1, 1].
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        cm: Sampler,
        steerer: Steerer,
        task: Task,
        starts: Tensor,
        num_envs: int = 64,
        seed: int = 0,
        action_penalty: float = 0.0,
        motion_penalty: float = 0.0,
        observe: str = "frame",
        max_turn_rate: float | None = None,
    ) -> None:
        if observe not in OBSERVATIONS:
            raise ValueError(f"observe must be one of {OBSERVATIONS}, got {observe!r}")
        D = cm.dim
        # the frames every reset() starts from: finite and in feature units, or refused here
        starts = check_frames("starts", starts, D, ndim=(2,), shape_words=f"(P, {D})")
        self.cm, self.steerer, self.task = cm, steerer, task
        self.action_penalty = check_number("action_penalty", action_penalty, low=0.0)
        self.motion_penalty = check_number("motion_penalty", motion_penalty, low=0.0)
        self.max_turn_rate = (
            None
            if max_turn_rate is None
            else check_number("max_turn_rate", max_turn_rate, low=0.0, low_open=True)
        )
        measurable = cm.skeleton is not None and cm.layout is not None
        if self.motion_penalty and not measurable:
            raise ValueError("motion_penalty needs a base model with a skeleton and a layout")
        self.starts = cm.normalize(starts.to(cm.device))
        self.num_envs = check_int("num_envs", num_envs, low=1)
        self.generator = torch.Generator(device="cpu").manual_seed(seed)
        self.task.setup(self.num_envs, self.generator)
        self.observe = observe
        self._seen: list[int] | None = None  # the frame dimensions the policy sees (None: all)
        if observe == "root":
            if cm.layout is None:
                raise ValueError('observe="root" needs a base model with a feature layout')
            vel = cm.layout.root_vel
            self._seen = [*range(vel.start, vel.stop), cm.layout.yaw_rate.start]
        obs_dim = (D if self._seen is None else len(self._seen)) + task.obs_dim
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (steerer.action_dim,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.x = torch.zeros(self.num_envs, D, device=cm.device)
        self.ch = Characters.zeros(self.num_envs, cm.fps)
        self.returns = torch.zeros(self.num_envs)
        self.turn = torch.zeros(self.num_envs)  # yaw rate (rad/frame), averaged over TURN_FRAMES
        self._rot_sl = (
            (cm.layout.root_vel, cm.layout.yaw_rate) if cm.layout else (slice(0, 2), slice(2, 3))
        )
        self.quality = _FrameQuality(cm, starts, self.num_envs) if measurable else None

    # -- state --------------------------------------------------------------------------

    def _reset_rows(self, idx: Tensor) -> None:
        pick = torch.randint(len(self.starts), (len(idx),), generator=self.generator)
        self.x[idx] = self.starts[pick]
        self.ch.xy[idx] = 0
        self.ch.heading[idx] = 0
        self.ch.velocity[idx] = self._root_motion(self.x[idx], self.ch.heading[idx])[0]
        self.ch.frame[idx] = 0
        self.returns[idx] = 0
        self.turn[idx] = 0
        self.task.reset(idx, self.ch)
        if self.quality is not None:
            self.quality.reset(idx, self._feats(self.x[idx]), self.ch.xy[idx], self.ch.heading[idx])

    def _feats(self, x: Tensor) -> Tensor:
        return self.cm.denormalize(x).float().cpu()

    def _root_motion(self, x: Tensor, heading: Tensor) -> tuple[Tensor, Tensor]:
        """World velocity (M, 2) m/s and yaw rate (M,) of normalized frames x in heading frame
        ``heading`` + yaw rate (the frame's own heading)."""
        feats = self._feats(x)
        vel, yaw = feats[:, self._rot_sl[0]], feats[:, self._rot_sl[1]][:, 0]
        world = rotate_about_z(vel, heading + yaw)  # the step of decode_root, (M, 2)
        return world * self.cm.fps, yaw

    def _obs(self) -> np.ndarray:
        x = self.x if self._seen is None else self.x[:, self._seen]
        obs = torch.cat([x.float().cpu(), self.task.observe(self.ch)], dim=1)
        return obs.numpy().astype(np.float32)

    # -- gymnasium API --------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Restart every environment from random corpus frames (re-seeded if ``seed``)."""
        if seed is not None:
            self.generator.manual_seed(int(seed))
        self._reset_rows(torch.arange(self.num_envs))
        return self._obs(), {}

    def advance(self, actions: Tensor) -> tuple[Tensor, Tensor]:
        """Step every character one frame with ``actions`` (N, A): returns the new frames
        (N, D) normalized and the previous root positions (N, 2). No task, no reset."""
        x = self.steerer(self.x, actions.to(self.cm.device), self.generator)
        if (bad := _non_finite_row(x)) is not None:
            raise FloatingPointError(f"the model produced a non-finite frame for environment {bad}")
        prev = self.ch.xy.clone()
        vel, yaw = self._root_motion(x, self.ch.heading)
        self.ch.heading = wrap_angle(self.ch.heading + yaw, include_pi=False)
        self.turn = self.turn + (yaw.float().cpu() - self.turn) / TURN_FRAMES
        self.ch.velocity = vel
        self.ch.xy = self.ch.xy + vel / self.cm.fps
        self.ch.frame = self.ch.frame + 1
        self.x = x
        return x, prev

    def score(self, actions: Tensor, prev: Tensor) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """The task's reward for the frame just made, less the penalties: ``(reward (N,),
        terminated (N,), info)``. The info has the task's own ``task_reward`` and, with the base
        model's skeleton known, the frame's ``bone_cm`` and ``slide_cm`` (whatever the
        penalties)."""
        reward, terminated, info = self.task.step(self.ch, prev)
        info = {**info, "task_reward": reward}
        if self.max_turn_rate is not None:
            spun = self.turn.abs() * self.cm.fps > math.radians(self.max_turn_rate)
            terminated = terminated | spun
            info = {**info, "spun": spun}
        reward = reward - self.action_penalty * actions.pow(2).mean(1)
        if self.quality is not None:
            bone, slide = self.quality(self._feats(self.x), self.ch.xy, self.ch.heading)
            reward = reward - self.motion_penalty * (bone + slide)
            info = {**info, "bone_cm": bone, "slide_cm": slide}
        return reward, terminated, info

    def step(self, actions):
        a = check_actions(actions, self.num_envs, self.single_action_space.shape[0])
        a = a.clamp(-1.0, 1.0)
        _, prev = self.advance(a)
        reward, terminated, info = self.score(a, prev)
        truncated = (self.ch.frame >= self.task.max_frames) & ~terminated
        self.returns += reward
        obs = self._obs()
        infos: dict[str, Any] = {k: v.numpy() for k, v in info.items()}
        done = terminated | truncated
        if done.any():
            idx = done.nonzero()[:, 0]
            infos["final_obs"] = obs.copy()
            infos["_final_obs"] = done.numpy()
            infos["episode_return"] = self.returns.numpy().copy()
            infos["episode_length"] = self.ch.frame.numpy().copy()
            self._reset_rows(idx)
            obs = self._obs()
        return (
            obs,
            reward.numpy().astype(np.float64),
            terminated.numpy(),
            truncated.numpy(),
            infos,
        )


class SteeringEnv(gym.Env):
    """One character: a :class:`SteeringVecEnv` with ``num_envs=1`` as a plain ``gym.Env``.

    Episodes end (terminated or truncated) instead of restarting by themselves. Used by
    gymnasium's ``check_env`` and by interactive demos.
    """

    metadata = {"render_modes": []}

    def __init__(self, cm, steerer, task, starts, seed: int = 0, **penalties: float):
        self.vec = SteeringVecEnv(cm, steerer, task, starts, 1, seed, **penalties)
        self.observation_space = self.vec.single_observation_space
        self.action_space = self.vec.single_action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, info = self.vec.reset(seed=seed, options=options)
        return obs[0], info

    def step(self, action):
        a = check_actions(np.asarray(action)[None], 1, self.action_space.shape[0]).clamp(-1, 1)
        v = self.vec
        _, prev = v.advance(a)
        reward, terminated, info = v.score(a, prev)
        truncated = bool(v.ch.frame[0] >= v.task.max_frames) and not bool(terminated[0])
        return (
            v._obs()[0],
            float(reward[0]),
            bool(terminated[0]),
            truncated,
            {k: t[0].item() for k, t in info.items()},
        )
