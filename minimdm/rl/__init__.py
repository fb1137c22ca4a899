"""Hierarchical RL steering of a frozen motion model (A-MDM §5–6, eqs. 6–8; chapter 7).

* :mod:`~minimdm.rl.residual`: the residual hook :math:`\\tilde x^t = \\hat x^t + w^t a^t`
  (eq. 7) and its schedule (which steps, which features, the annealing of :math:`w^t`);
* :mod:`~minimdm.rl.tasks`: target reaching, joystick control (eq. 8), path following (§6);
* :mod:`~minimdm.rl.env`: the gymnasium vector environment (one batched model call steps every
  character), the residual and MVAE-latent steerers, the per-frame motion penalty (bone length
  error + foot sliding), a single-character view;
* :mod:`~minimdm.rl.train`: stable-baselines3 PPO through a ``VecEnv`` adapter (eq. 6);
* :mod:`~minimdm.rl.policy`: policies stored as safetensors + JSON, loaded with their base model.
"""

from .env import LatentSteerer, ResidualSteerer, SteeringEnv, SteeringVecEnv, check_actions
from .policy import PolicyNet, Steering, fingerprint, load_steering
from .residual import ResidualSchedule, feature_indices, residual_hook
from .tasks import (
    Characters,
    JoystickTask,
    PathTask,
    TargetTask,
    joystick_reward,
    make_task,
    procedural_paths,
)

__all__ = [
    "ResidualSchedule",
    "residual_hook",
    "feature_indices",
    "Characters",
    "TargetTask",
    "JoystickTask",
    "PathTask",
    "make_task",
    "joystick_reward",
    "procedural_paths",
    "ResidualSteerer",
    "LatentSteerer",
    "SteeringVecEnv",
    "SteeringEnv",
    "check_actions",
    "PolicyNet",
    "Steering",
    "fingerprint",
    "load_steering",
]
