"""Checkpoints: safetensors weights with JSON metadata beside them, written atomically.

A checkpoint with stem ``runs/amdm/model`` is up to three files:

* ``model.safetensors`` — the weights used for sampling (the EMA weights when training kept
  them). Its header also carries the full metadata, so this one file is a complete, consistent
  checkpoint on its own.
* ``model.json`` — the same metadata, readable: the training config and the config file that
  made it, the feature layout, the skeleton, the normalizer statistics, the library version, the
  training steps and how to rebuild the network.
* ``model.train.safetensors`` (optional) — everything a resumed run needs: raw and EMA weights,
  optimizer state and random-generator states, plus the metadata. It is self-contained, so a
  crash between writing two files never mixes states.

Nothing is pickled: tensors go through safetensors, everything else through JSON. Every file is
written to a temporary file in the same folder, synced and then renamed over the old one with
``os.replace`` (:func:`minimdm.files.atomic_write`), so an interrupted save leaves the last good
checkpoint intact. Loading checks what a file holds before it is used (:mod:`minimdm.bounds`):
sizes, schedule, frame rates and normalizer statistics in bounds, floating-point weights (half
precision only where the metadata records it), finite parameters.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import math
import os
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save
from torch import Tensor, nn

from minimdm._version import __version__
from minimdm.bounds import STORAGE, metadata_problem, parameter_problem, tensor_problem
from minimdm.files import atomic_write
from minimdm.validate import InputError, MismatchError

__all__ = [
    "FORMAT",
    "DEFAULT_FPS",
    "Checkpoint",
    "CheckpointMismatchError",
    "CheckpointError",
    "checkpoint_paths",
    "save_checkpoint",
    "load_checkpoint",
    "load_train_state",
    "resume_training",
    "update_metadata",
    "model_spec",
    "build_model",
    "register_model_kind",
    "fingerprint",
    "check_same_model",
]

FORMAT = "minimdm-checkpoint/1"
"""Format tag written into every checkpoint's metadata."""

DEFAULT_FPS = 30.0
"""The frame rate of a checkpoint that records none (every corpus the book ships is 30 fps)."""

_META_KEY = "minimdm"  # safetensors header key holding the metadata JSON
_DEFAULT_STEM = "model"  # file stem used when a folder is given


class CheckpointMismatchError(MismatchError):
    """A checkpoint was made for another feature layout or skeleton than the one expected."""


class CheckpointError(InputError):
    """A checkpoint file that cannot be read: empty, truncated, not safetensors (a pickle, say),
    a broken header, or weights that do not fit the network its metadata describes. The message
    names the file and what is wrong with it."""


# --------------------------------------------------------------------------------------------
# Model kinds: how to describe a network in JSON and rebuild it.


_BUILDERS: dict[str, Callable[[dict], nn.Module]] = {}
_SPECS: list[tuple[type, str, Callable[[nn.Module], dict]]] = []

KIND_MODULES: dict[str, str] = {
    "amdm": "minimdm.amdm.models",
    "mse": "minimdm.amdm.models",
    "mvae": "minimdm.amdm.models",
    "camdm": "minimdm.camdm.model",
    "style_classifier": "minimdm.camdm.classifier",
    "ddgan": "minimdm.aamdm.model",
    "ddgan_generator": "minimdm.aamdm.nets",
    "aamdm_motion": "minimdm.aamdm.motion",
    "policy": "minimdm.rl.nets",
}
"""Where each shipped network kind is defined. That module registers its kind when it is
imported (:func:`register_model_kind`); :func:`build_model` imports it on first use, so that
``import minimdm`` loads none of them."""


def register_model_kind(
    kind: str, cls: type, build: Callable[[dict], nn.Module], spec: Callable[[nn.Module], dict]
) -> None:
    """Teach checkpoints a new network kind.

    ``spec(model)`` returns its JSON config, ``build(config)`` rebuilds it.
    """
    _BUILDERS[kind] = build
    _SPECS.insert(0, (cls, kind, spec))


def model_spec(model: nn.Module) -> dict:
    """``{"kind": ..., "config": {...}}``: the JSON that :func:`build_model` rebuilds from."""
    for cls, kind, spec in _SPECS:
        if isinstance(model, cls):
            return {"kind": kind, "config": spec(model)}
    known = ", ".join(c.__name__ for c, _, _ in _SPECS)
    raise ValueError(f"model must be one of {known} (or registered), got {type(model).__name__}")


def build_model(spec: dict) -> nn.Module:
    """Rebuild a network from :func:`model_spec`'s output (weights not loaded)."""
    if not isinstance(spec, dict):
        raise ValueError(f"model spec must be a dict with 'kind' and 'config', got {spec!r}")
    kind = spec.get("kind")
    if kind not in _BUILDERS and isinstance(kind, str) and kind in KIND_MODULES:
        importlib.import_module(KIND_MODULES[kind])  # registers the kind
    if kind not in _BUILDERS:
        known = sorted(set(_BUILDERS) | set(KIND_MODULES))
        raise ValueError(f"model kind must be one of {known}, got {kind!r}")
    config = spec.get("config")
    if not isinstance(config, dict):
        raise ValueError(f"model config of kind {kind!r} must be a dict, got {config!r}")
    try:
        return _BUILDERS[kind](dict(config))
    except (TypeError, ValueError, KeyError) as e:  # unknown or missing keys, bad values
        raise ValueError(f"model config {config} does not build a {kind!r} network: {e}") from e


def fingerprint(model: nn.Module) -> str:
    """A short hash of a network's weights (names, shapes and bytes), independent of its file."""
    h = hashlib.sha256()
    for name, t in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().cpu().contiguous().float().numpy().tobytes())
    return h.hexdigest()[:16]


def check_same_model(name: str, graph: Any, model: nn.Module, kind: str, where: str) -> None:
    """:class:`~minimdm.validate.InputError` when ``graph`` (a fast path such as
    :class:`minimdm.fast.FastFrame`, whose ``metadata["checkpoint"]`` records the kind, name and
    :func:`fingerprint` of the checkpoint it was exported from) was made from another network
    than ``model`` (of kind ``kind``, from ``where``), naming both. Anything without such a
    record (a plain function, a graph exported before fingerprints) is not compared."""
    meta = getattr(graph, "metadata", None)
    made_from = meta.get("checkpoint") if isinstance(meta, dict) else None
    if not isinstance(made_from, dict) or not made_from.get("fingerprint"):
        return
    have = fingerprint(model)
    if (made_from.get("kind"), made_from["fingerprint"]) != (kind, have):
        raise InputError(
            f"{name} runs a graph exported from another model: checkpoint "
            f"{made_from.get('name')!r} (kind {made_from.get('kind')}, weights "
            f"{made_from['fingerprint']}), but the model given is {where} (kind {kind}, weights "
            f"{have}); export the graph from this model (minimdm.fast.fast_frame(checkpoint))"
        )


# --------------------------------------------------------------------------------------------
# Paths.


@dataclass(frozen=True)
class CheckpointPaths:
    """The files of one checkpoint."""

    weights: Path
    """``STEM.safetensors``: sampling weights plus metadata in the header."""
    meta: Path
    """``STEM.json``: the readable metadata."""
    train: Path
    """``STEM.train.safetensors``: the resumable training state."""


def checkpoint_paths(path: str | os.PathLike) -> CheckpointPaths:
    """The files for ``path``: a folder (stem ``model`` inside it), a stem, or one of the files."""
    p = Path(path)
    if p.is_dir() or str(path).endswith(os.sep):
        p = p / _DEFAULT_STEM
    name = p.name
    for suffix in (".train.safetensors", ".safetensors", ".json"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    stem = p.with_name(name)
    return CheckpointPaths(
        weights=stem.with_name(name + ".safetensors"),
        meta=stem.with_name(name + ".json"),
        train=stem.with_name(name + ".train.safetensors"),
    )


# --------------------------------------------------------------------------------------------
# JSON and nested tensor state.


def _jsonable(x: Any) -> Any:
    """Turn tensors, numpy values, dataclass-likes and paths into JSON values."""
    if isinstance(x, Tensor):
        return x.detach().cpu().tolist()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    if hasattr(x, "to_dict"):
        return _jsonable(x.to_dict())
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if x is None or isinstance(x, (bool, int, float, str)):
        return x
    raise TypeError(f"cannot store a {type(x).__name__} in checkpoint metadata")


def _pack(obj: Any, tensors: dict[str, Tensor], key: str) -> Any:
    """Replace every tensor in a nested structure by a reference into ``tensors``."""
    if isinstance(obj, Tensor):
        tensors[key] = obj.detach().cpu().contiguous().clone()
        return {"__tensor__": key}
    if isinstance(obj, dict):
        if all(isinstance(k, str) for k in obj):
            return {"__dict__": {k: _pack(v, tensors, f"{key}.{k}") for k, v in obj.items()}}
        return {"__items__": [[k, _pack(v, tensors, f"{key}.{k}")] for k, v in obj.items()]}
    if isinstance(obj, tuple):
        return {"__tuple__": [_pack(v, tensors, f"{key}.{i}") for i, v in enumerate(obj)]}
    if isinstance(obj, list):
        return [_pack(v, tensors, f"{key}.{i}") for i, v in enumerate(obj)]
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    raise TypeError(f"cannot store a {type(obj).__name__} at {key!r} of the training state")


def _unpack(obj: Any, tensors: dict[str, Tensor]) -> Any:
    if isinstance(obj, list):
        return [_unpack(v, tensors) for v in obj]
    if isinstance(obj, dict):
        if "__tensor__" in obj:
            return tensors[obj["__tensor__"]]
        if "__dict__" in obj:
            return {k: _unpack(v, tensors) for k, v in obj["__dict__"].items()}
        if "__items__" in obj:
            return {k: _unpack(v, tensors) for k, v in obj["__items__"]}
        if "__tuple__" in obj:
            return tuple(_unpack(v, tensors) for v in obj["__tuple__"])
    return obj


def _dumps(meta: dict) -> str:
    return json.dumps(meta, indent=1, sort_keys=True, allow_nan=False)


# --------------------------------------------------------------------------------------------
# Save.


def save_checkpoint(
    path: str | os.PathLike,
    model: nn.Module,
    metadata: dict | None = None,
    optimizer_state: dict | None = None,
    storage: str = "float32",
) -> CheckpointPaths:
    """Save ``model`` and its metadata atomically; returns the files written.

    Args:
        path: a folder (files ``model.*`` inside it) or a stem such as ``checkpoints/amdm``.
        model: the network to sample with (pass the EMA copy when there is one).
        metadata: JSON-able facts about the checkpoint. By convention: ``config`` (the training
            config), ``config_file``, ``feature_layout``, ``skeleton``, ``normalizer``,
            ``step``, ``diffusion`` (schedule kind, T, predicts). Objects with ``to_dict``,
            tensors and numpy arrays are converted. ``format``, ``minimdm_version`` and
            ``model`` (kind and config, from :func:`model_spec`) are added.
        optimizer_state: optional training state for resuming: a nested dict / list / tuple of
            tensors and JSON values (optimizer ``state_dict``, raw weights, generator states,
            step...). Stored in ``STEM.train.safetensors``, which is written first.
        storage: ``"float16"`` or ``"bfloat16"`` stores the sampling weights in half precision
            (half the bytes) and records it as ``storage``; loading restores float32. The
            training state always keeps full precision.
    """
    if storage not in STORAGE:
        raise InputError(f"storage must be one of {', '.join(STORAGE)}, got {storage!r}")
    paths = checkpoint_paths(path)
    meta = _jsonable(dict(metadata or {}))
    meta.update(format=FORMAT, minimdm_version=__version__, model=model_spec(model))
    if storage != "float32":
        meta["storage"] = storage
    text = _dumps(meta)
    if optimizer_state is not None:
        tensors: dict[str, Tensor] = {}
        tree = _pack(optimizer_state, tensors, "s")
        header = {_META_KEY: text, "train_state": json.dumps(tree)}
        atomic_write(paths.train, st_save(tensors, metadata=header))
    dtype = STORAGE[storage]
    weights = {
        k: v.detach().cpu().to(dtype if v.is_floating_point() else v.dtype).contiguous().clone()
        for k, v in model.state_dict().items()
    }
    atomic_write(paths.weights, st_save(weights, metadata={_META_KEY: text}))
    atomic_write(paths.meta, (text + "\n").encode())
    return paths


# --------------------------------------------------------------------------------------------
# Load.


@dataclass
class Checkpoint:
    """A loaded checkpoint: the rebuilt network (in eval mode) and its metadata."""

    model: nn.Module
    """The network, weights loaded, in eval mode."""
    metadata: dict
    """Everything :func:`save_checkpoint` stored (see its docstring)."""
    paths: CheckpointPaths
    """The files it came from."""
    extra: dict = field(default_factory=dict)
    """Free room for callers (e.g. a cached decoder)."""

    @property
    def kind(self) -> str:
        """``"amdm"``, ``"mse"``, ``"mvae"`` or a registered kind."""
        return self.metadata["model"]["kind"]

    @property
    def step(self) -> int:
        """Training steps the weights have seen."""
        return int(self.metadata.get("step", 0))

    @property
    def config(self) -> dict:
        """The training config as a dict (``minimdm.amdm.train.TrainConfig(**ckpt.config)``)."""
        return dict(self.metadata.get("config") or {})

    @property
    def feature_layout(self) -> dict | None:
        return self.metadata.get("feature_layout")

    @property
    def skeleton(self) -> dict | None:
        return self.metadata.get("skeleton")

    @property
    def normalizer(self) -> dict | None:
        return self.metadata.get("normalizer")

    @property
    def fps(self) -> float:
        """The frame rate of the motion it learnt: its config's, else its feature layout's."""
        layout = self.feature_layout if isinstance(self.feature_layout, dict) else {}
        return float(self.config.get("fps") or layout.get("fps") or DEFAULT_FPS)

    @property
    def diffusion(self) -> dict:
        """A denoiser's sampler settings as stored: ``schedule``, ``T``, ``predicts`` and
        ``clip_x0`` (the clamp it was trained with); empty for the other kinds."""
        return dict(self.metadata.get("diffusion") or {})

    def schedule(self, device: torch.device | str = "cpu"):
        """The :class:`~minimdm.diffusion.NoiseSchedule` the denoiser was trained with."""
        from minimdm.diffusion import NoiseSchedule

        d = self.metadata.get("diffusion")
        if not d:
            raise ValueError(
                f"checkpoint {self.paths.weights} is not a diffusion model ({self.kind})"
            )
        return NoiseSchedule(d["schedule"], int(d["T"]), device=device)


def _diagnose(path: Path) -> str:
    """Why ``path`` is not a safetensors file, in words, from its first bytes and its size."""
    size = path.stat().st_size
    if size == 0:
        return "it is empty (0 bytes): an interrupted copy?"
    with open(path, "rb") as f:
        head = f.read(16)
    if size < 8:
        return f"it is truncated: {size} bytes, less than a safetensors header"
    n = int.from_bytes(head[:8], "little")
    if head[8:9] != b"{":  # a safetensors header is JSON after its 8-byte length
        if (head[:1] == b"\x80" and head[1:2] in (b"\x02", b"\x03", b"\x04", b"\x05")) or (
            head[:4] == b"PK\x03\x04"
        ):
            return (
                "it looks like a pickle or torch.save file, which minimdm never loads "
                "(unpickling runs code); convert the weights to safetensors"
            )
        return "it is not a safetensors file (it does not start with a safetensors header)"
    if n > size - 8:
        return f"it is truncated: its header needs {n} bytes, but the file holds {size - 8} more"
    try:
        with open(path, "rb") as f:
            f.seek(8)
            entries = json.loads(f.read(n))
        end = max(
            (e["data_offsets"][1] for k, e in entries.items() if k != "__metadata__"), default=0
        )
    except (ValueError, KeyError, TypeError, IndexError):
        return "its safetensors header is damaged (not the JSON a safetensors file starts with)"
    if size < 8 + n + end:
        return f"it is truncated: {size} bytes, but its header describes {8 + n + end}"
    return "its safetensors header or data is damaged (overwritten?)"


def _open_safetensors(path: Path, tensors: bool = True) -> tuple[dict, dict[str, Tensor]]:
    """The header metadata of a safetensors file and (with ``tensors``) its tensors on the CPU;
    :class:`CheckpointError` naming the file and what is wrong with it."""
    from safetensors import SafetensorError

    try:
        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
        # st_load of the bytes (not safe_open's memory map) keeps the file closed afterwards
        return header, (st_load(path.read_bytes()) if tensors else {})
    except (FileNotFoundError, IsADirectoryError):
        raise
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"cannot read checkpoint file {path}: {_diagnose(path)} ({e})") from e


def _header_json(path: Path, header: dict, key: str) -> Any:
    try:
        return json.loads(header[key])
    except json.JSONDecodeError as e:
        raise CheckpointError(
            f"checkpoint file {path}: its {key!r} header is not valid JSON ({e}); the file is "
            "damaged"
        ) from e


def _read_header_meta(path: Path) -> dict:
    header, _ = _open_safetensors(path, tensors=False)
    if _META_KEY not in header:
        raise CheckpointError(f"{path} is not a minimdm checkpoint (no '{_META_KEY}' metadata)")
    meta = _header_json(path, header, _META_KEY)
    if not isinstance(meta, dict):
        raise CheckpointError(f"checkpoint file {path}: its metadata is not a JSON object")
    return meta


def _check_fit(path: Path, meta: dict, own: dict[str, Tensor], state: dict[str, Tensor]) -> None:
    """:class:`CheckpointError` naming ``path`` and the first tensor of the file that is missing,
    unexpected, of another shape or of a wrong dtype for the network's tensors ``own``."""
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        raise CheckpointError(
            f"checkpoint file {path}: its weights do not fit the network its metadata describes "
            f"({meta['model'].get('kind')}): missing tensors {missing[:5]}, unexpected tensors "
            f"{unexpected[:5]}"
        )
    for k, v in own.items():
        if tuple(state[k].shape) != tuple(v.shape):
            raise CheckpointError(
                f"checkpoint file {path}: its weights do not fit the network its metadata "
                f"describes: tensor {k!r} has shape {tuple(state[k].shape)} in the file, but the "
                f"network needs {tuple(v.shape)}"
            )
    if problem := tensor_problem(own, state, meta.get("storage", "float32")):
        raise CheckpointError(f"checkpoint file {path}: {problem}")


def _build_and_load(path: Path, meta: dict, state: dict[str, Tensor]) -> nn.Module:
    """The network ``meta["model"]`` describes, with ``state`` loaded; :class:`CheckpointError`
    naming ``path`` and what is wrong: metadata out of bounds (:mod:`minimdm.bounds`), or a
    tensor that is missing, unexpected, of another shape or dtype, or not finite.

    The network is first built on the ``meta`` device (nothing allocated) and compared with the
    file, so that metadata describing a huge network fails before any memory is taken."""
    if "model" not in meta:
        raise CheckpointError(
            f"checkpoint file {path}: its metadata has no 'model' entry (the network's kind "
            "and config), so the network cannot be rebuilt"
        )
    if problem := metadata_problem(meta):
        raise CheckpointError(f"checkpoint file {path}: {problem}")
    checked = False
    try:
        with torch.device("meta"):
            _check_fit(path, meta, build_model(meta["model"]).state_dict(), state)
        checked = True
    except ValueError as e:
        if isinstance(e, CheckpointError):
            raise
        raise CheckpointError(f"checkpoint file {path}: {e}") from e
    except (RuntimeError, NotImplementedError):  # a builder that computes on its tensors
        pass  # (the sizes in its config are bounded); compared once it is built
    try:
        model = build_model(meta["model"])
    except ValueError as e:
        raise CheckpointError(f"checkpoint file {path}: {e}") from e
    if not checked:
        _check_fit(path, meta, model.state_dict(), state)
    model.load_state_dict(state, strict=True)  # half-precision storage becomes float32 here
    if problem := parameter_problem(model):
        raise CheckpointError(f"checkpoint file {path}: {problem}")
    return model


def _canonical(x: Any) -> Any:
    return json.loads(json.dumps(_jsonable(x), sort_keys=True))


def _first_difference(a: Any, b: Any, where: str = "") -> str | None:
    """Where two JSON values first differ (floats compared to 1e-6), or None."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                return f"{where}.{k}: only in {'the checkpoint' if k in a else 'the expected'}"
            d = _first_difference(a[k], b[k], f"{where}.{k}")
            if d:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{where}: length {len(a)} vs {len(b)}"
        for i, (u, v) in enumerate(zip(a, b, strict=True)):
            d = _first_difference(u, v, f"{where}[{i}]")
            if d:
                return d
        return None
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return None if math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-6) else f"{where}: {a} vs {b}"
    return None if a == b else f"{where}: {a!r} vs {b!r}"


def _summary(x: Any, limit: int = 300) -> str:
    text = json.dumps(x, sort_keys=True, separators=(",", ":"))
    return text if len(text) <= limit else text[:limit] + "...}"


def _check_expected(what: str, stored: Any, expected: Any, path: Path) -> None:
    if expected is None:
        return
    exp = _canonical(expected)
    if stored is None:
        raise CheckpointMismatchError(
            f"checkpoint {path} records no {what}, but the expected {what} is {_summary(exp)}"
        )
    diff = _first_difference(stored, exp)
    if diff:
        raise CheckpointMismatchError(
            f"checkpoint {path} was made for another {what}.\n"
            f"  checkpoint's {what}: {_summary(stored)}\n"
            f"  expected {what}:     {_summary(exp)}\n"
            f"  first difference (checkpoint vs expected) at {diff.lstrip('.')}"
        )


def load_checkpoint(
    path: str | os.PathLike,
    expected_layout: Any = None,
    expected_skeleton: Any = None,
    device: torch.device | str = "cpu",
) -> Checkpoint:
    """Load a checkpoint written by :func:`save_checkpoint` and rebuild its network.

    Args:
        path: the folder, the stem or any of the checkpoint's files.
        expected_layout: the feature layout the caller will feed (a ``FeatureLayout`` or its
            ``to_dict()``); if the checkpoint's differs, raise :class:`CheckpointMismatchError`
            naming both.
        expected_skeleton: likewise for the skeleton.
        device: where to put the network.

    The metadata are read from the weights file's header, which is written in one atomic step
    with the weights; the JSON file beside it is the readable copy.
    """
    paths = checkpoint_paths(path)
    if not paths.weights.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}: expected the file {paths.weights}")
    meta = _read_header_meta(paths.weights)
    if meta.get("format") != FORMAT:
        raise CheckpointError(
            f"checkpoint {paths.weights} has format {meta.get('format')!r}, expected {FORMAT!r}"
        )
    if paths.meta.exists():
        try:
            beside = json.loads(paths.meta.read_text())
        except json.JSONDecodeError:
            beside = None
        if beside != meta:
            warnings.warn(
                f"{paths.meta} does not match the metadata inside {paths.weights} "
                "(an interrupted save?); using the weights file's metadata",
                stacklevel=2,
            )
    _check_expected("feature layout", meta.get("feature_layout"), expected_layout, paths.weights)
    _check_expected("skeleton", meta.get("skeleton"), expected_skeleton, paths.weights)
    _, state = _open_safetensors(paths.weights)
    model = _build_and_load(paths.weights, meta, state)
    model.to(device).eval()
    return Checkpoint(model=model, metadata=meta, paths=paths)


def load_train_state(path: str | os.PathLike) -> tuple[dict, dict]:
    """Read ``STEM.train.safetensors``: returns ``(metadata, training_state)``.

    ``training_state`` is the nested structure given to :func:`save_checkpoint` as
    ``optimizer_state``, with its tensors restored on the CPU.
    """
    paths = checkpoint_paths(path)
    if not paths.train.is_file():
        raise FileNotFoundError(f"no training state at {path}: expected the file {paths.train}")
    header, tensors = _open_safetensors(paths.train)
    if _META_KEY not in header or "train_state" not in header:
        raise CheckpointError(f"{paths.train} is not a minimdm training state")
    meta = _header_json(paths.train, header, _META_KEY)
    tree = _header_json(paths.train, header, "train_state")
    try:
        return meta, _unpack(tree, tensors)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(
            f"training state {paths.train}: its tensor index does not match its tensors ({e!r}); "
            "the file is damaged"
        ) from e


def resume_training(
    out_dir: str | os.PathLike,
    config: dict,
    model: Any,
    optimizer: Any,
    generator: torch.Generator,
    ema: Any = None,
    resumable: Iterable[str] = (),
    defaults: dict | None = None,
) -> tuple[int, float]:
    """Continue an interrupted training run from ``out_dir``'s training state, if it has one.

    The saved run's config must equal ``config`` except for the ``resumable`` keys (budgets,
    intervals, device): resuming with another model or learning rate would mix two runs, so it
    raises, naming each difference. A key the saved config lacks (a field added since the run
    started) counts as its value in ``defaults``. Loads the model, the optimizer, the EMA copy
    (if given) and the batch generator in place.

    Returns:
        ``(step, seconds)``: the step to continue from and the training time already spent,
        ``(0, 0.0)`` when ``out_dir`` holds no training state.
    """
    paths = checkpoint_paths(out_dir)
    if not paths.train.exists():
        return 0, 0.0
    meta, state = load_train_state(out_dir)
    saved = {**{k: v for k, v in (defaults or {}).items() if k in config}, **meta.get("config", {})}
    keys = sorted((set(saved) | set(config)) - set(resumable))
    diff = [
        f"{k}: {saved.get(k)!r} vs {config.get(k)!r}" for k in keys if saved.get(k) != config.get(k)
    ]
    if diff:
        raise ValueError(
            f"cannot resume from {paths.train}: its config differs from this run's "
            f"(saved vs now): {'; '.join(diff)}. Use another out_dir or resume=False."
        )
    model.load_state_dict(state["model"])
    if ema is not None:
        ema.load_state_dict(state["ema"])
    optimizer.load_state_dict(state["optimizer"])
    generator.set_state(state["generator"].to(torch.uint8))
    return int(state["step"]), float(meta.get("train_seconds", 0.0))


def update_metadata(
    path: str | os.PathLike, edit: Callable[[dict], dict | None]
) -> CheckpointPaths:
    """Rewrite a checkpoint's metadata in place; the weights stay bit for bit the same.

    ``edit(metadata)`` changes the metadata dict (or returns a new one). The network is rebuilt
    from the edited ``model`` spec and loaded with the stored weights before anything is written,
    so an edit that no longer fits the weights raises and leaves the files as they were. Then
    the weights file (tensors plus new header) and the JSON beside it are written atomically,
    the weights file first. A training state (``STEM.train.safetensors``) is left untouched.
    """
    paths = checkpoint_paths(path)
    if not paths.weights.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}: expected the file {paths.weights}")
    meta = _read_header_meta(paths.weights)
    _, tensors = _open_safetensors(paths.weights)
    edited = edit(meta)
    meta = _jsonable(meta if edited is None else edited)
    _build_and_load(paths.weights, meta, tensors)  # the edit still fits the weights
    text = _dumps(meta)
    atomic_write(paths.weights, st_save(tensors, metadata={_META_KEY: text}))
    atomic_write(paths.meta, (text + "\n").encode())
    return paths
