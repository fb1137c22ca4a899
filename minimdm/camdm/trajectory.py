"""The run-time trajectories of CAMDM (Chen et al. 2024, §3.2 and Figure 3).

* :func:`spring_positions` and :func:`spring_headings`: the user's synthetic future trajectory,
  a critically damped spring from the character's current velocity (and turning rate) towards
  the joystick's (Büttner and Clavet 2015; Holden's "spring-roll-call" closed forms);
  :func:`spring_path` steps the same spring frame by frame under a goal that changes;
* :func:`blend_trajectories`: the model's predicted trajectory blended with the user's, more of
  the user's the further ahead (Holden et al. 2017);
* :func:`extend_trajectory`: heuristic future trajectory extension (HFTE): when M frames of a
  plan have been applied, its predicted trajectory is M points short; the last K points are
  recycled, mirrored about the last point, until the length matches;
* :func:`inertialize`: the same spring, used to absorb the jump from one plan to the next (our
  addition to CAMDM's controller, not in the paper).

All are batched over characters: positions ``(B, n, 2)`` on the ground, headings ``(B, n)`` in
radians, times in seconds.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from minimdm.motion.skeleton import rotate_about_z, to_heading_frame, wrap_angle

__all__ = [
    "halflife_to_damping",
    "spring_positions",
    "spring_path",
    "spring_headings",
    "blend_trajectories",
    "extend_trajectory",
    "inertialize",
]


def halflife_to_damping(halflife: float) -> float:
    """The damping of a critically damped spring that halves its error in ``halflife`` s."""
    return 4.0 * math.log(2.0) / (halflife + 1e-5)


def spring_positions(
    xy: Tensor, velocity: Tensor, goal_velocity: Tensor, halflife: float, times: Tensor
) -> Tensor:
    """Future ground positions ``(B, n, 2)`` of a point at ``xy (B, 2)`` moving at ``velocity
    (B, 2)`` whose velocity a critically damped spring pulls to ``goal_velocity (B, 2)``, at
    ``times (n,)`` seconds ahead (zero initial acceleration)."""
    y = halflife_to_damping(halflife) / 2
    t = times.to(xy)[None, :, None]  # (1, n, 1)
    j0 = (velocity - goal_velocity)[:, None]  # (B, 1, 2)
    j1 = j0 * y
    e = torch.exp(-y * t)
    drift = e * (-j1 / y**2 + (-j0 - j1 * t) / y) + j1 / y**2 + j0 / y  # (B, n, 2), from j0
    return drift + goal_velocity[:, None] * t + xy[:, None]


def spring_path(goal_velocity: Tensor, halflife: float, dt: float) -> Tensor:
    """The ground path ``(B, N + 1, 2)`` that a joystick draws over N frames: the velocity follows
    ``goal_velocity (B, N, 2)``, which may change every frame, through the critically damped
    spring of :func:`spring_positions`, stepped ``dt`` seconds at a time from the origin, moving
    at the first goal. Each step is the spring's exact solution over ``dt`` (its velocity and
    acceleration carry over, so a goal that changes mid-turn stays smooth); positions add up
    the velocity at the end of each step. Benchmarks turn preset commands into the root path
    that inpainting follows and CAMDM's user trajectory would draw."""
    y = halflife_to_damping(halflife) / 2
    e = math.exp(-y * dt)
    v, a = goal_velocity[:, 0].clone(), torch.zeros_like(goal_velocity[:, 0])
    xy = [torch.zeros_like(v)]
    for f in range(goal_velocity.shape[1]):
        j0 = v - goal_velocity[:, f]
        j1 = a + j0 * y
        v = e * (j0 + j1 * dt) + goal_velocity[:, f]
        a = e * (a - j1 * y * dt)
        xy.append(xy[-1] + v * dt)
    return torch.stack(xy, 1)


def spring_headings(
    heading: Tensor, rate: Tensor, goal: Tensor, halflife: float, times: Tensor
) -> Tensor:
    """Future headings ``(B, n)`` of a critically damped spring from ``heading (B,)`` turning at
    ``rate (B,)`` rad/s towards ``goal (B,)``, the short way round, at ``times (n,)``."""
    y = halflife_to_damping(halflife) / 2
    t = times.to(heading)[None]  # (1, n)
    target = heading + wrap_angle(goal - heading)  # the goal nearest to the heading
    j0 = (heading - target)[:, None]
    j1 = rate[:, None] + j0 * y
    return torch.exp(-y * t) * (j0 + j1 * t) + target[:, None]


def blend_trajectories(
    predicted_xy: Tensor,
    predicted_heading: Tensor,
    user_xy: Tensor,
    user_heading: Tensor,
    bias: float = 1.0,
) -> tuple[Tensor, Tensor]:
    """The controlling trajectory: point k of n is :math:`(1 - w_k)` predicted + :math:`w_k`
    user with :math:`w_k = (k / n)^{bias}` (headings blended by their wrapped difference)."""
    n = predicted_xy.shape[1]
    w = (torch.arange(1, n + 1, dtype=predicted_xy.dtype, device=predicted_xy.device) / n) ** bias
    xy = predicted_xy + w[None, :, None] * (user_xy - predicted_xy)
    heading = predicted_heading + w[None] * wrap_angle(user_heading - predicted_heading)
    return xy, heading


def _travel_direction(xy: Tensor, heading: Tensor) -> Tensor:
    """The direction of travel at the last point, (B,), from a second-order backward difference
    (exact on lines, near-exact on circles); the heading where the path stands still."""
    if xy.shape[1] >= 3:
        d = 1.5 * xy[:, -1] - 2.0 * xy[:, -2] + 0.5 * xy[:, -3]
    else:
        d = xy[:, -1] - xy[:, -2]
    still = d.norm(dim=-1) < 1e-6
    return torch.where(still, heading[:, -1], torch.atan2(d[:, 1], d[:, 0]))


def extend_trajectory(
    xy: Tensor, heading: Tensor, length: int, K: int = 15
) -> tuple[Tensor, Tensor]:
    """HFTE (Figure 3): extend a trajectory ``(B, n, 2)``, ``(B, n)`` to ``length`` points.

    Each recycle takes the last ``K`` points before the last one and mirrors them about the
    line through the last point across the direction of travel: the point j steps before the
    end becomes the point j steps after it, and its heading is mirrored likewise (:math:`2
    \\theta_n - \\theta_{n-j}`). A straight line continues straight, a circle as a circle of the
    same radius, a sideways walk sideways. Recycles repeat until the length is reached.
    """
    if xy.shape[1] < 2:
        raise ValueError(f"a trajectory needs at least 2 points to extend, got {xy.shape[1]}")
    if K < 1:
        raise ValueError(f"K must be >= 1, got {K}")
    while xy.shape[1] < length:
        m = min(K, xy.shape[1] - 1, length - xy.shape[1])
        last, h_last = xy[:, -1:], heading[:, -1:]  # (B, 1, 2), (B, 1)
        d = _travel_direction(xy, heading)  # (B,)
        prev = xy[:, -1 - m : -1].flip(1) - last  # (B, m, 2): the points 1..m steps back
        along, across = to_heading_frame(prev, d).unbind(-1)  # in the travel frame
        along = -along  # the mirror: behind becomes ahead
        new_xy = last + rotate_about_z(torch.stack([along, across], -1), d)
        back = heading[:, -1 - m : -1].flip(1)  # (B, m)
        new_h = h_last + wrap_angle(h_last - back)  # 2 theta_n - theta_{n-j}
        xy, heading = torch.cat([xy, new_xy], 1), torch.cat([heading, new_h], 1)
    return xy[:, :length], heading[:, :length]


def inertialize(source: Tensor, target: Tensor, halflife: float, fps: float) -> Tensor:
    """Spring inertialization: ``target (B, n, D)`` made to start where ``source (B, >= 2, D)``
    starts, moving as it moves, and to become the target through a critically damped spring.

    The offset that is added begins as the gap :math:`\\Delta_0 = s_0 - x_0` between the first
    frames, with the gap in velocity :math:`\\dot\\Delta_0 = ((s_1 - s_0) - (x_1 - x_0))\\,
    \\mathrm{fps}`, and dies out with ``halflife`` (seconds), like :func:`spring_positions`'s
    error; at frame j, :math:`t_j = j / \\mathrm{fps}`:

    .. math:: x_j + e^{-y t_j}\\,\\big(\\Delta_0 + (\\dot\\Delta_0 + y \\Delta_0)\\, t_j\\big),
              \\qquad y = \\tfrac12\\,\\mathrm{damping}(\\mathrm{halflife}).

    Any feature vector works (positions, 6D rotations); a 6D rotation that comes out slightly
    off orthonormal is read through Gram-Schmidt anyway. Inertialization is Bollo's (GDC 2016);
    the spring form follows Holden's "spring-roll-call" notes.
    """
    y = halflife_to_damping(halflife) / 2
    t = torch.arange(target.shape[1], dtype=target.dtype, device=target.device) / fps
    t = t[None, :, None]  # (1, n, 1)
    gap = source[:, :1] - target[:, :1]  # (B, 1, D)
    gap_v = ((source[:, 1:2] - source[:, :1]) - (target[:, 1:2] - target[:, :1])) * fps
    return target + torch.exp(-y * t) * (gap + (gap_v + gap * y) * t)
