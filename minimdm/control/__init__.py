"""Control without retraining (A-MDM §4.2-4.3): task-oriented sampling, inpainting, inbetweening.

Each technique drives the one reverse chain of :mod:`minimdm.diffusion` frame after frame,
through :meth:`minimdm.amdm.sampling.Sampler.frame`; none copies it:

* :func:`beam_search` samples a pool of candidate futures per frame and keeps the first frame of
  the best under a score function (:mod:`~minimdm.control.scores`);
* :func:`inpaint` passes the hook of eq. 4 (:func:`~minimdm.control.hooks.inpaint_hook`), which
  overwrites the user's features after every reverse step; :mod:`~minimdm.control.targets`
  builds targets and masks from root paths and joint trajectories;
* :func:`inbetween` starts each frame's chain from the noised keyframe at
  :math:`t_0 = (1 - f/N)\\,t_{max}` (eq. 5); :func:`lerp_inbetween` is the linear baseline.

All three take a loaded :class:`~minimdm.checkpoint.Checkpoint` (or a
:class:`~minimdm.amdm.sampling.Sampler`) and return a :class:`Motion`, whose ``positions`` are
the global joints, (F, J, 3) for one character.
"""

from minimdm.amdm.sampling import Sampler

from .beam import Future, beam_search
from .core import Motion, regressor_noise
from .hooks import inbetween_t_start, inpaint_hook
from .inpaint import inbetween, inpaint, lerp_inbetween
from .scores import combine, heading_score, reached, speed_score, target_score
from .targets import (
    Constraint,
    circle_path,
    clip_frame,
    figure_eight_path,
    joint_height_targets,
    joint_path_targets,
    polyline_path,
    root_path_targets,
)

__all__ = [
    "Sampler",
    "Motion",
    "regressor_noise",
    "Future",
    "beam_search",
    "target_score",
    "heading_score",
    "speed_score",
    "combine",
    "reached",
    "inpaint_hook",
    "inbetween_t_start",
    "inpaint",
    "inbetween",
    "lerp_inbetween",
    "Constraint",
    "root_path_targets",
    "joint_height_targets",
    "joint_path_targets",
    "circle_path",
    "figure_eight_path",
    "polyline_path",
    "clip_frame",
]
