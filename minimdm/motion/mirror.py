"""Left/right mirroring of a clip: the same motion reflected through a vertical plane.

A mirrored take doubles the data and balances it: every left turn gets its right turn, every
step that leads with the left foot one that leads with the right. The reflection must keep a
valid skeleton, so it is done on the joints' rotations, not on the features:

* the world is reflected by :math:`M = \\mathrm{diag}(1, -1, 1)` (a vertical plane; the heading
  frame of the A-MDM features makes the choice of plane irrelevant), so the root moves along
  :math:`M p`;
* joint ``k`` of the mirrored pose takes the global rotation of its partner ``j`` (``_L`` for
  ``_R`` and so on; a centre joint is its own partner), reflected:
  :math:`G'_k = M\\,G_j\\,C_k`, where :math:`C_k` is a fixed reflection of the joint's own frame.

With parents mirrored too, the local rotations become :math:`R'_k = C_{p(k)}^\\top R_j C_k`. For
the positions to be the mirror image, :math:`C_k` must map the rest offset of each child ``c``
to that of the child's partner, :math:`C_k o_c = o_{\\bar c}`. BVH rigs keep their joint frames
aligned with axes but not always mirrored (the Bandai-Namco rig's left leg points along +y, its
right leg along -y), so :math:`C_k` is chosen among the four axis reflections (a diagonal of
signs with determinant -1) that satisfy the offsets; where several do (a joint with one child
or none), the one whose mirrored rotations look most like the partner's own in the clip wins
(twist about a bone is invisible in the offsets, visible in the data). A pair of partners
shares one :math:`C`, so mirroring twice gives the clip back.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

from .data import Clip
from .skeleton import Skeleton, matrix_to_quat, quat_to_matrix

__all__ = ["joint_partners", "mirror_frames", "mirror_clip", "mirror_clips"]

_LEFT, _RIGHT = "Left left _L _l L_ l_ .L .l".split(), "Right right _R _r R_ r_ .R .r".split()
_SIDES = tuple(zip(_LEFT, _RIGHT, strict=True))  # (left, right) spellings of a side
_WORLD = np.diag([1.0, -1.0, 1.0])  # M: reflect the world's y axis
_FLIPS = [np.diag(s) for s in itertools.product((1.0, -1.0), repeat=3) if np.prod(s) < 0]


def joint_partners(skeleton: Skeleton) -> list[int]:
    """The mirror partner of every joint: ``Foot_L`` for ``Foot_R`` (also ``Left``/``Right``,
    ``left``/``right``, ``L_``/``R_`` and the like); a joint without one is its own."""
    names = skeleton.names
    out = []
    for name in names:
        partner = name
        for a, b in _SIDES:
            for x, y in ((a, b), (b, a)):
                if x in name and name.replace(x, y, 1) in names:
                    partner = name.replace(x, y, 1)
                    break
            if partner != name:
                break
        out.append(names.index(partner))
    for j, p in enumerate(out):
        if out[p] != j:
            raise ValueError(f"joint names pair up inconsistently: {names[j]} -> {names[p]}")
    return out


def mirror_frames(skeleton: Skeleton, local_rot: np.ndarray, tol: float = 0.1) -> list[np.ndarray]:
    """The reflection :math:`C_k` (3, 3) of each joint frame (see the module docstring).

    ``local_rot`` (F, J, 4) is a clip's rotations, used only to settle a choice the offsets leave
    open. ``tol`` is the relative mismatch allowed between a child's offset and its partner's
    (actors are not exactly symmetric).
    """
    partner = joint_partners(skeleton)
    R = quat_to_matrix(torch.as_tensor(local_rot, dtype=torch.float64)).numpy()  # (F, J, 3, 3)
    mean_R = R.mean(0)  # (J, 3, 3): chordal mean of each joint's local rotation
    off = skeleton.offsets
    children = [skeleton.children(k) for k in range(len(skeleton))]
    C: list[np.ndarray | None] = [None] * len(skeleton)
    for k in range(len(skeleton)):
        if C[k] is not None:
            continue
        j = partner[k]

        def fits(Ck: np.ndarray, k: int = k) -> bool:
            return all(
                np.linalg.norm(Ck @ off[c] - off[partner[c]]) <= tol * np.linalg.norm(off[c]) + 1e-3
                for c in children[k]
            )

        ok = [Ck for Ck in _FLIPS if fits(Ck) and (j == k or fits(Ck, j))]
        if not ok:
            raise ValueError(
                f"cannot mirror the skeleton: no axis reflection of {skeleton.names[k]}'s frame "
                "maps its children's rest offsets onto their partners'"
            )
        p = skeleton.parents[k]
        Cp = C[p] if p >= 0 else _WORLD  # the root's parent frame is the world

        def cost(Ck: np.ndarray, Cp: np.ndarray = Cp, k: int = k, j: int = j) -> float:
            d = np.linalg.norm(Cp.T @ mean_R[j] @ Ck - mean_R[k])  # partner mirrored vs own
            return float(d + np.linalg.norm(Cp.T @ mean_R[k] @ Ck - mean_R[j]))

        C[k] = C[j] = min(ok, key=cost)
    return C  # type: ignore[return-value]


def mirror_clip(
    clip: Clip, frames: list[np.ndarray] | None = None, name: str | None = None
) -> Clip:
    """The clip reflected left/right (see the module docstring); named ``NAME~mirror``.

    ``frames`` are the joint-frame reflections of :func:`mirror_frames` (default: settled on
    this clip alone; :func:`mirror_clips` settles them once for a whole corpus). Joint positions
    are the mirror images of the original's, up to the actor's own asymmetry (left and right
    bones of slightly different lengths).
    """
    sk = clip.skeleton
    partner = joint_partners(sk)
    C = np.stack(frames if frames is not None else mirror_frames(sk, clip.local_rot))  # (J,3,3)
    R = quat_to_matrix(torch.as_tensor(clip.local_rot, dtype=torch.float64)).numpy()
    R = R[:, partner]  # (F, J, 3, 3): each joint takes its partner's rotation
    Cp = np.stack([C[p] if p >= 0 else _WORLD for p in sk.parents])  # (J, 3, 3)
    R_m = np.swapaxes(Cp, -1, -2)[None] @ R @ C[None]  # C_p^T R_j C_k
    quats = matrix_to_quat(torch.from_numpy(R_m)).numpy()
    return Clip(
        name or f"{clip.name}~mirror",
        clip.fps,
        sk,
        clip.root_pos @ _WORLD.T,
        quats,
        None,
        clip.loop,
        dict(clip.labels),
    )


def mirror_clips(clips: list[Clip]) -> list[Clip]:
    """Every clip mirrored, with one set of joint-frame reflections settled on all of them (the
    clips must share a topology; a choice settled per clip can differ between clips)."""
    clips = list(clips)
    if not clips:
        return []
    frames = mirror_frames(clips[0].skeleton, np.concatenate([c.local_rot for c in clips]))
    return [mirror_clip(c, frames) for c in clips]
