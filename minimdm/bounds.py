"""What a checkpoint may hold: the bounds :func:`minimdm.checkpoint.load_checkpoint` checks.

A checkpoint is data from a file, and a file can be damaged, hand-edited or made by something
else. Loading must not turn such a file into a crash (a schedule of a billion steps, a network
too large for memory) or into silent garbage (integer weights, a normalizer that divides by
zero or multiplies by 1e30). So before the network is built, and again once its weights are
read, every field that sizes an allocation or scales a result is checked against what this
library ever writes:

* the network's sizes (every integer of the model config) up to :data:`MAX_SIZE`;
* the diffusion schedule: ``T`` in [1, :data:`MAX_T`], ``predicts`` one of
  :data:`~minimdm.diffusion.PREDICTS`, ``clip_x0`` None, a finite number > 0 or a per-feature
  range of finite numbers with lo <= hi;
* frame rates in [1, 1000] frames per second;
* normalizer statistics (``mean``, ``std`` and ``floor`` of every normalizer, and the pairs of
  ``X_mean`` / ``X_std`` buffers of a network): finite, the standard deviations in
  (0, :data:`MAX_STD`];
* the weights: floating point where the network's are (float32, or float16 / bfloat16 storage
  that the metadata records under ``storage``), the network's own dtype elsewhere, and finite
  parameters.

Each function returns what is wrong, in words, or None; the loader names the file.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any

import torch
from torch import Tensor

from minimdm.diffusion.schedule import PREDICTS

__all__ = [
    "MAX_SIZE",
    "MAX_T",
    "MAX_STD",
    "FPS_RANGE",
    "STORAGE",
    "metadata_problem",
    "tensor_problem",
    "parameter_problem",
]

MAX_SIZE = 1 << 16
"""The largest integer a network's config may hold (widths, depths, latent sizes, steps)."""
MAX_T = 10_000
"""The most diffusion steps a checkpoint may declare."""
MAX_STD = 1e6
"""The largest standard deviation a normalizer may hold (features are metres and radians)."""
FPS_RANGE = (1.0, 1000.0)
"""Frame rates a checkpoint may declare (as BVH files may)."""
STORAGE = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}
"""Weight storage a checkpoint may record under ``storage`` (float32 when it records none)."""


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _ints(x: Any, where: str) -> Iterator[tuple[str, int]]:
    """Every integer in a JSON value, with its dotted place."""
    if isinstance(x, Mapping):
        for k, v in x.items():
            yield from _ints(v, f"{where}.{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from _ints(v, f"{where}[{i}]")
    elif isinstance(x, int) and not isinstance(x, bool):
        yield where, x


def _normalizers(x: Any, where: str) -> Iterator[tuple[str, Mapping]]:
    """Every mapping with ``mean`` and ``std`` in a JSON value (nested ones too)."""
    if isinstance(x, Mapping):
        if "mean" in x and "std" in x:
            yield where, x
        for k, v in x.items():
            if isinstance(v, (Mapping, list)):
                yield from _normalizers(v, f"{where}.{k}")


def _flat(x: Any) -> list | None:
    """A list of numbers (nested lists flattened), or None if it holds anything else."""
    out: list = []
    stack = [x]
    while stack:
        v = stack.pop()
        if isinstance(v, list):
            stack.extend(reversed(v))
        elif _is_number(v):
            out.append(float(v))
        else:
            return None
    return out


def _stats_problem(where: str, mean: Any, std: Any) -> str | None:
    """Mean and std (numbers or lists): finite, std in (0, MAX_STD]."""
    m, s = _flat(mean), _flat(std)
    if m is None or s is None:
        return f"{where} must hold lists of numbers for mean and std"
    for i, v in enumerate(m):
        if not math.isfinite(v) or abs(v) > MAX_STD:
            return f"{where}.mean[{i}] must be finite and within ±{MAX_STD:g}, got {v:g}"
    for i, v in enumerate(s):
        if not (math.isfinite(v) and 0 < v <= MAX_STD):
            return f"{where}.std[{i}] must be a finite number in (0, {MAX_STD:g}], got {v:g}"
    if len(m) != len(s):
        return f"{where} has {len(m)} means but {len(s)} standard deviations"
    return None


def _clip_problem(clip: Any) -> str | None:
    if clip is None:
        return None
    if _is_number(clip):
        if math.isfinite(clip) and clip > 0:
            return None
        return f"diffusion.clip_x0 must be None, a finite number > 0 or a range, got {clip!r}"
    if isinstance(clip, list) and len(clip) == 2:
        lo, hi = _flat(clip[0]), _flat(clip[1])
        if lo is not None and hi is not None and len(lo) == len(hi):
            ok = [
                math.isfinite(a) and math.isfinite(b) and a <= b
                for a, b in zip(lo, hi, strict=True)
            ]
            bad = [i for i, good in enumerate(ok) if not good]
            if not bad:
                return None
            i = bad[0]
            return (
                f"diffusion.clip_x0 must be a range of finite numbers with lo <= hi, but feature "
                f"{i} has [{lo[i]:g}, {hi[i]:g}]"
            )
    return "diffusion.clip_x0 must be None, a finite number > 0 or a [lo, hi] pair of lists"


def metadata_problem(meta: Mapping[str, Any]) -> str | None:
    """What is out of bounds in a checkpoint's metadata (module docstring), or None."""
    spec = meta.get("model")
    if isinstance(spec, Mapping):
        for where, v in _ints(spec.get("config"), "model.config"):
            if abs(v) > MAX_SIZE:
                return (
                    f"{where} = {v} is beyond {MAX_SIZE} (the sizes of a network this library "
                    "builds); the metadata is damaged"
                )
    diff = meta.get("diffusion")
    if isinstance(diff, Mapping):
        T = diff.get("T")
        T_ok = isinstance(T, int) and not isinstance(T, bool) and 1 <= T <= MAX_T
        if T is not None and not T_ok:
            return f"diffusion.T must be an integer in [1, {MAX_T}], got {T!r}"
        if diff.get("predicts") not in (None, *PREDICTS):
            return f"diffusion.predicts must be one of {PREDICTS}, got {diff.get('predicts')!r}"
        if problem := _clip_problem(diff.get("clip_x0")):
            return problem
    for key in ("config", "feature_layout", "data"):
        part = meta.get(key)
        fps = part.get("fps") if isinstance(part, Mapping) else None
        if fps is not None and not (_is_number(fps) and FPS_RANGE[0] <= fps <= FPS_RANGE[1]):
            lo, hi = FPS_RANGE
            return f"{key}.fps must be a frame rate in [{lo:g}, {hi:g}], got {fps!r}"
    for where, norm in _normalizers(meta.get("normalizer"), "normalizer"):
        if problem := _stats_problem(where, norm["mean"], norm["std"]):
            return problem
        floor = norm.get("floor")
        if floor is not None and not (_is_number(floor) and 0 < floor <= MAX_STD):
            return f"{where}.floor must be a number in (0, {MAX_STD:g}], got {floor!r}"
    storage = meta.get("storage", "float32")
    if storage not in STORAGE:
        return f"storage must be one of {', '.join(STORAGE)}, got {storage!r}"
    return None


def tensor_problem(
    own: Mapping[str, Tensor], state: Mapping[str, Tensor], storage: str = "float32"
) -> str | None:
    """What is wrong with the file's tensors ``state`` for a network whose own tensors are
    ``own`` (names, shapes, dtypes; meta tensors will do), or None."""
    kind = STORAGE.get(storage, torch.float32)
    for k, v in own.items():
        got = state[k].dtype
        if v.is_floating_point():
            if got not in (torch.float32, torch.float64, torch.float16, torch.bfloat16):
                return (
                    f"tensor {k!r} is stored as {str(got).removeprefix('torch.')}, but the "
                    "network's weights are floating point (float32, or float16 / bfloat16 "
                    "storage); the file is damaged or not made by minimdm"
                )
            if got in (torch.float16, torch.bfloat16) and got != kind:
                return (
                    f"tensor {k!r} is stored as {str(got).removeprefix('torch.')}, but the "
                    f"metadata records storage {storage!r}; a checkpoint stored in half "
                    "precision records it (save_checkpoint(..., storage='float16'))"
                )
        elif got != v.dtype:
            return f"tensor {k!r} is stored as {got}, but the network holds {v.dtype}"
        if k.endswith("std") and k[:-3] + "mean" in state and v.is_floating_point():
            mean, std = (state[n].double().flatten().tolist() for n in (k[:-3] + "mean", k))
            if problem := _stats_problem(k[:-3] + "mean/std", mean, std):  # a normalizer buffer
                return problem
    return None


def parameter_problem(model: torch.nn.Module) -> str | None:
    """The first parameter that holds NaN or Inf, in words, or None."""
    for name, p in model.named_parameters():
        if not torch.isfinite(p).all():
            return f"parameter {name!r} holds NaN or Inf; the weights are damaged"
    return None
