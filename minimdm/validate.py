"""Checks of user input, once each: every public entry point validates its arguments with these.

The design's error policy is that bad input gets a clear error that says what was expected and
where, and that nothing is lost. So every check here raises before any work is done, and its
message has one shape: ``"{argument} must be {expected}, got {what it got}"``.

* :class:`InputError` (a ``ValueError``) and :class:`InputTypeError` (a ``TypeError``) are what
  the checks raise. The ``minimdm`` command prints them, and every other ``ValueError`` of the
  library, as one line ``minimdm CMD: error: ...`` with exit code 2; any other exception is a
  bug and keeps its traceback.
* :func:`check_int`, :func:`check_number`, :func:`check_choice`, :func:`check_device` and
  :func:`check_generator` check scalars and the sources of randomness and computation.
* :func:`check_frames` and :func:`check_mask` check feature tensors: type, shape, finiteness and
  magnitude (:data:`MAX_FEATURE`).
* :func:`check_skeleton` compares the skeleton and frame rate a start pose or clip came from with
  the ones a model was trained on (:class:`MismatchError`, naming both and the first
  difference).
* :func:`check_output_file` and :func:`check_output_dir` check where results will be written,
  before the sampling or training that makes them.
"""

from __future__ import annotations

import math
import numbers
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

__all__ = [
    "InputError",
    "InputTypeError",
    "MismatchError",
    "MAX_FEATURE",
    "describe",
    "check_int",
    "check_number",
    "check_choice",
    "check_device",
    "check_generator",
    "check_frames",
    "check_mask",
    "check_skeleton",
    "skeleton_difference",
    "describe_skeleton",
    "check_output_file",
    "check_output_dir",
]

MAX_FEATURE = 1e4
"""The largest magnitude a frame feature may have (metres, metres per frame, radians, 6D
components). Real frames stay within a few units; anything beyond this is not a pose."""


class InputError(ValueError):
    """A public entry point got a bad value; the message names the argument, what was expected
    and what it got."""


class InputTypeError(TypeError):
    """A public entry point got a value of the wrong type; the message names the argument, the
    expected type and what it got."""


class MismatchError(InputError):
    """Input made for another skeleton, feature layout or frame rate than the model's; the
    message names both and the first difference."""


def describe(value: Any, limit: int = 80) -> str:
    """``value`` for an error message: its repr (shortened) and, for scalars, its type.

    Tensors and arrays are described by shape and dtype, not by their contents.
    """
    if isinstance(value, Tensor):
        return f"a tensor of shape {tuple(value.shape)} ({value.dtype})"
    if hasattr(value, "shape") and hasattr(value, "dtype"):  # numpy arrays
        return f"an array of shape {tuple(value.shape)} ({value.dtype})"
    text = repr(value)
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    if value is None or isinstance(value, (str, bool, int, float, list, tuple, dict)):
        return f"{text} ({type(value).__name__})"
    return f"{text} (a {type(value).__name__})"


def _bad(name: str, expected: str, value: Any, cls: type[Exception] = InputError) -> Exception:
    return cls(f"{name} must be {expected}, got {describe(value)}")


def _range_words(low: Any, high: Any, low_open: bool = False) -> str:
    lo = f"> {low}" if low_open else f">= {low}"
    if low is not None and high is not None:
        return f"in [{low}, {high}]" if not low_open else f"in ({low}, {high}]"
    if low is not None:
        return lo
    if high is not None:
        return f"<= {high}"
    return ""


def check_int(name: str, value: Any, *, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an ``int``; a bool, a float (even a whole one) or a string is refused.

    Raises:
        InputTypeError: not an integer (``steps=2.5``, ``n_frames=True``).
        InputError: outside ``[low, high]``.
    """
    bounds = _range_words(low, high)
    expected = f"an integer {bounds}".rstrip()
    if isinstance(value, Tensor) and value.dim() == 0 and not value.dtype.is_floating_point:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise _bad(name, expected, value, InputTypeError)
    value = int(value)
    if (low is not None and value < low) or (high is not None and value > high):
        raise _bad(name, expected, value)
    return value


def check_number(
    name: str,
    value: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
) -> float:
    """``value`` as a finite ``float`` in ``[low, high]`` (``(low, high]`` with ``low_open``).

    Raises:
        InputTypeError: not a real number (a bool or a string is refused).
        InputError: NaN, Inf or out of range.
    """
    bounds = _range_words(low, high, low_open)
    expected = f"a finite number {bounds}".rstrip()
    if isinstance(value, Tensor) and value.dim() == 0:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise _bad(name, expected, value, InputTypeError)
    x = float(value)
    if not math.isfinite(x):
        raise _bad(name, expected, value)
    if low is not None and (x <= low if low_open else x < low):
        raise _bad(name, expected, value)
    if high is not None and x > high:
        raise _bad(name, expected, value)
    return x


def check_choice(name: str, value: Any, choices: Iterable[Any]) -> Any:
    """``value`` if it is one of ``choices``, else :class:`InputError` listing them."""
    options = list(choices)
    if isinstance(value, bool) or value not in options:
        raise _bad(name, "one of " + ", ".join(repr(c) for c in options), value)
    return value


def check_device(name: str, value: Any) -> torch.device | None:
    """``value`` (None, a string such as ``"cpu"`` / ``"cuda:0"``, or a ``torch.device``) as a
    device this machine has; None stays None.

    Raises:
        InputTypeError: not a string or device.
        InputError: an unknown device name, or CUDA / MPS when this torch cannot use them.
    """
    if value is None:
        return None
    if not isinstance(value, (str, torch.device)):
        raise _bad(name, "a device such as 'cpu' or 'cuda'", value, InputTypeError)
    try:
        device = torch.device(value)
    except (RuntimeError, ValueError):
        raise _bad(name, "a device such as 'cpu' or 'cuda'", value) from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(
                f"{name} must be a device this machine has, got {str(value)!r}: this torch "
                "build sees no CUDA GPU (use 'cpu')"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise InputError(
                f"{name} must name one of the {torch.cuda.device_count()} CUDA devices, "
                f"got {str(value)!r}"
            )
    elif device.type == "mps":
        if not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
            raise InputError(f"{name} must be a device this machine has, got {str(value)!r}")
    elif device.type != "cpu":
        raise _bad(name, "'cpu', 'cuda' or 'mps'", value)
    return device


def check_generator(
    name: str, value: Any, device: torch.device | str | None = None
) -> torch.Generator | None:
    """``value`` if it is None or a ``torch.Generator`` on ``device``'s type.

    A seed is refused with a hint: pass ``torch.Generator().manual_seed(seed)``.
    """
    if value is None:
        return None
    if not isinstance(value, torch.Generator):
        hint = ""
        if isinstance(value, numbers.Integral) and not isinstance(value, bool):
            hint = f" (for a seed, pass torch.Generator().manual_seed({int(value)}))"
        raise InputTypeError(
            f"{name} must be a torch.Generator or None, got {describe(value)}{hint}"
        )
    if device is not None and value.device.type != torch.device(device).type:
        raise InputError(
            f"{name} must be a generator on the sampling device ({torch.device(device).type}), "
            f"got a generator on {value.device.type}"
        )
    return value


def _as_float_tensor(name: str, value: Any, expected: str) -> Tensor:
    if isinstance(value, (str, bytes)) or value is None:
        raise _bad(name, expected, value, InputTypeError)
    try:
        x = torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError):
        raise _bad(name, expected, value, InputTypeError) from None
    if x.dtype == torch.bool or x.is_complex():
        raise InputTypeError(f"{name} must be {expected}, got a tensor of {x.dtype}")
    return x.to(torch.float32)


def check_frames(
    name: str,
    value: Any,
    dim: int | None,
    *,
    joints: Sequence[str] | None = None,
    ndim: Sequence[int] = (1, 2),
    shape_words: str | None = None,
    allow_nan: bool = False,
) -> Tensor:
    """Frames in feature units as a float32 tensor: shape ``(..., D)``, finite, within
    :data:`MAX_FEATURE`, with a non-empty batch.

    Args:
        name: the argument, for messages ("init_states", "start", "keyframe"...).
        value: a tensor, an array or nested lists of numbers.
        dim: D, the model's frame dimension (None: any).
        joints: the model's joint names; a wrong D then says which skeleton the frames fit.
        ndim: the accepted numbers of dimensions.
        shape_words: how to say the accepted shapes (default ``(D,) or (B, D)``).
        allow_nan: let NaN through (targets outside a mask); Inf and huge values never pass.
    """
    words = shape_words or f"({dim},) or (B, {dim})"
    x = _as_float_tensor(name, value, f"frames of shape {words} (a tensor of numbers)")
    if x.dim() not in ndim or (dim is not None and x.shape[-1] != dim):
        msg = f"{name} must have shape {words}, got {tuple(x.shape)}"
        if dim is not None and x.dim() in ndim and joints is not None:
            J, rest = divmod(x.shape[-1] - 3, 12)
            fits = f"a {J}-joint skeleton" if not rest and J >= 1 else "no skeleton (3 + 12 J)"
            shown = ", ".join(list(joints)[:4]) + (", ..." if len(joints) > 4 else "")
            msg += (
                f": the model's frames have D = 3 + 12 J = {dim} for its {len(joints)} joints "
                f"({shown}), but D = {x.shape[-1]} fits {fits}. Encode motion of the model's "
                "skeleton (minimdm.motion.features.encode)"
            )
        raise InputError(msg)
    if x.dim() > 1 and any(s == 0 for s in x.shape[:-1]):
        raise InputError(f"{name} must hold at least one frame, got shape {tuple(x.shape)}")
    bad = torch.isinf(x) if allow_nan else ~torch.isfinite(x)
    if bad.any():
        where = bad.nonzero()[0].tolist()
        got = f"{name}{where} is {x[tuple(where)].item()}"
        if x.dim() == 2:
            got = f"character {where[0]} holds NaN/Inf ({got})"
        raise InputError(f"{name} must be finite, but {got}")
    big = torch.nan_to_num(x.abs(), nan=0.0) > MAX_FEATURE
    if big.any():
        where = big.nonzero()[0].tolist()
        raise InputError(
            f"{name} must hold frames in feature units (metres, radians; every value within "
            f"±{MAX_FEATURE:g}), but {name}{where} is {x[tuple(where)].item():.3g}"
        )
    return x


def check_mask(name: str, value: Any) -> Tensor:
    """A 0/1 mask as a bool tensor: bools, or numbers that are exactly 0 or 1."""
    if isinstance(value, (str, bytes)) or value is None:
        raise _bad(name, "a 0/1 or bool tensor", value, InputTypeError)
    try:
        m = torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError):
        raise _bad(name, "a 0/1 or bool tensor", value, InputTypeError) from None
    if m.dtype != torch.bool:
        if m.is_complex():
            raise InputTypeError(f"{name} must be a 0/1 or bool tensor, got {m.dtype}")
        off = ~((m == 0) | (m == 1))
        if off.any():
            where = off.nonzero()[0].tolist() if m.dim() else []
            got = m[tuple(where)].item() if where else m.item()
            raise InputError(
                f"{name} must be binary (0/1 or bool), but {name}{where or ''} is {got!r}"
            )
    return m.to(torch.bool)


def describe_skeleton(names: Sequence[str], parents: Sequence[int] | None = None) -> str:
    """``"a 15-joint skeleton (root, chest, neck, right_hip, ...)"``."""
    shown = ", ".join(list(names)[:5]) + (", ..." if len(names) > 5 else "")
    return f"a {len(names)}-joint skeleton ({shown})"


def skeleton_difference(
    a_names: Sequence[str],
    a_parents: Sequence[int] | None,
    b_names: Sequence[str],
    b_parents: Sequence[int] | None,
) -> str | None:
    """The first joint where two skeletons' names or parents differ, in words (None: same)."""
    for i, (na, nb) in enumerate(zip(a_names, b_names, strict=False)):
        pa = a_parents[i] if a_parents is not None else None
        pb = b_parents[i] if b_parents is not None else None
        if na != nb or pa != pb:
            return f"joint {i} is {na!r} (parent {pa}) vs {nb!r} (parent {pb})"
    if len(a_names) != len(b_names):
        return f"{len(a_names)} vs {len(b_names)} joints"
    return None


def check_skeleton(
    name: str,
    given: Any,
    expected: Any,
    *,
    given_fps: float | None = None,
    expected_fps: float | None = None,
    model: str = "the model",
) -> None:
    """Raise :class:`MismatchError` when ``given`` (the skeleton the input came from) is not
    ``expected`` (the model's): joint names and parents must agree (bone lengths may differ:
    actors do), and so must the frame rates when both are known.

    Both skeletons are anything with ``names`` and ``parents`` (a ``Skeleton``) or their dict;
    when either is None nothing is compared.
    """

    def parts(sk: Any) -> tuple[list[str], list[int] | None]:
        if isinstance(sk, dict):
            return list(sk.get("names") or sk.get("joint_names") or []), sk.get("parents")
        return list(sk.names), list(sk.parents)

    if given is not None and expected is not None:
        gn, gp = parts(given)
        en, ep = parts(expected)
        if gp is None or ep is None:
            gp = ep = None  # a layout knows names only
        diff = skeleton_difference(gn, gp, en, ep)
        if diff:
            raise MismatchError(
                f"{name} comes from another skeleton than {model}'s: {name} has "
                f"{describe_skeleton(gn)}, {model} {describe_skeleton(en)}; first difference: "
                f"{diff}. Start from motion of {model}'s skeleton"
            )
    if given_fps is not None and expected_fps is not None:
        if not math.isclose(float(given_fps), float(expected_fps), rel_tol=1e-3):
            raise MismatchError(
                f"{name} comes from motion at {given_fps:g} frames per second, but {model} "
                f"works at {expected_fps:g} (its velocities are per frame); resample the clip "
                f"first (minimdm.motion.data.resample_clip(clip, {expected_fps:g}))"
            )


def _check_writable_dir(name: str, folder: Path, value: Any) -> None:
    """The nearest existing ancestor of ``folder`` must be a folder we may write in."""
    probe = folder
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(
            f"{name} must be a path we can write to, got {str(value)!r}: {probe} is a file, "
            "not a folder"
        )
    try:  # permissions say too little (root, read-only mounts): try it
        fd, tmp = tempfile.mkstemp(dir=probe, prefix=".minimdm-write-test")
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise InputError(
            f"{name} must be a path we can write to, got {str(value)!r}: cannot write in "
            f"{probe} ({e.strerror or e})"
        ) from None


def check_output_file(name: str, value: Any, suffixes: Sequence[str] | None = None) -> Path:
    """``value`` as a ``Path`` to a file that can be written: a known suffix, not a folder, in a
    folder we may write in (made if missing). Checked before the work that fills it."""
    if not isinstance(value, (str, os.PathLike)) or str(value) == "":
        raise _bad(name, "a file path", value, InputTypeError)
    path = Path(value)
    if suffixes is not None and path.suffix.lower() not in suffixes:
        ends = f"{', '.join(suffixes[:-1])} or {suffixes[-1]}" if len(suffixes) > 1 else suffixes[0]
        raise InputError(f"{name} must end in {ends}, got {path.name!r}")
    if path.is_dir() or str(value).endswith(os.sep):
        raise InputError(f"{name} must be a file path, got {str(value)!r}, which is a folder")
    _check_writable_dir(name, path.parent, value)
    return path


def check_output_dir(name: str, value: Any) -> Path:
    """``value`` as a ``Path`` to a folder that exists or can be made, and that we may write in.
    Checked before the work that fills it."""
    if not isinstance(value, (str, os.PathLike)) or str(value) == "":
        raise _bad(name, "a folder path", value, InputTypeError)
    path = Path(value)
    if path.exists() and not path.is_dir():
        raise InputError(f"{name} must be a folder, got {str(value)!r}, which is a file")
    _check_writable_dir(name, path, value)
    return path
