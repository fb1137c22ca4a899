"""Training configs: a YAML or TOML file into a dataclass, with the types its fields declare.

Every trainer's config is a dataclass with one docstring per field (``TrainConfig``,
``AAMDMTrainConfig``); ``configs/*.yaml`` hold the runs. :func:`load_config` reads one file,
rejects keys the dataclass does not know (naming the key, the file and the known keys) and
converts values to the declared types, since YAML 1.1 reads ``5e-4`` as a string.
:func:`from_dict` does the same for a mapping, :func:`with_changes` for command-line overrides.
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml

__all__ = ["load_config", "from_dict", "with_changes"]

T = TypeVar("T")


def load_config(path: str | os.PathLike, cls: type[T]) -> T:
    """Read a ``.yaml``/``.yml`` or ``.toml`` file into the dataclass ``cls``.

    Unknown keys are an error; values are converted to the field types (:func:`from_dict`). A
    field named ``config_file`` that the file does not set records the file's path.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".yaml", ".yml", ".toml"):
        raise ValueError(f"{path}: a config must be a .yaml, .yml or .toml file")
    if not path.is_file():
        what = "is a folder" if path.is_dir() else "does not exist"
        raise FileNotFoundError(f"config file {path} {what}; expected a {suffix} file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(
            f"{path}: not a text file (byte {e.start} is not UTF-8); a config is a UTF-8 "
            f"{suffix} file"
        ) from None
    if "\x00" in text:
        raise ValueError(f"{path}: not a text file (it holds NUL bytes); expected a {suffix} file")
    if suffix == ".toml":
        try:
            data = _toml().loads(text)
        except ValueError as e:  # tomllib.TOMLDecodeError says the line and column
            raise ValueError(f"{path}: not valid TOML: {e}") from None
    else:
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            at = f":{mark.line + 1}" if mark is not None else ""
            problem = getattr(e, "problem", None) or str(e).splitlines()[0]
            raise ValueError(f"{path}{at}: not valid YAML: {problem}") from None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ValueError(
            f"{path} must hold a mapping of {cls.__name__} fields, got {type(data).__name__}"
        )
    if "config_file" in _fields(cls):
        data.setdefault("config_file", path.as_posix())
    return from_dict(cls, data, where=path.as_posix())


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = "config") -> T:
    """Build the dataclass ``cls`` from ``data``, converting values to the declared field types.

    ``int`` and ``float`` fields take numbers and numeric strings (``"5e-4"``); an ``int`` field
    takes a float only when it is whole. ``X | None`` fields take None, lists and tuples are
    converted element by element. ``where`` names the source in error messages.

    Raises:
        ValueError: an unknown key (named, with the known ones), a value of the wrong type, or
            one the dataclass refuses (its message, after ``where``).
    """
    fields = _fields(cls)
    if not all(isinstance(k, str) for k in data):
        bad = next(k for k in data if not isinstance(k, str))
        raise ValueError(f"{where}: config keys must be names, got {bad!r}")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(
            f"{where}: unknown config keys {unknown}; {cls.__name__} knows {sorted(fields)}"
        )
    hints = typing.get_type_hints(cls)
    values = {k: _coerce(v, hints[k], k, where) for k, v in data.items()}
    try:
        return cls(**values)
    except (ValueError, TypeError) as e:  # the dataclass's own checks (__post_init__)
        try:
            named = type(e)(f"{where}: {e}")
        except TypeError:  # an exception type that takes other arguments
            named = ValueError(f"{where}: {e}")
        raise named from None


def with_changes(config: T, changes: Mapping[str, Any], where: str = "overrides") -> T:
    """A copy of the dataclass instance ``config`` with the fields in ``changes`` replaced,
    checked and converted as by :func:`from_dict`."""
    current = {name: getattr(config, name) for name in _fields(type(config))}
    return from_dict(type(config), {**current, **changes}, where)


def _fields(cls: type) -> list[str]:
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"cls must be a dataclass, got {cls!r}")
    return [f.name for f in dataclasses.fields(cls) if f.init]


def _toml():
    try:
        import tomllib  # Python >= 3.11
    except ImportError:
        try:
            import tomli as tomllib
        except ImportError:
            raise ImportError("TOML configs need Python >= 3.11 or `pip install tomli`") from None
    return tomllib


def _type_name(tp: Any) -> str:
    return tp.__name__ if isinstance(tp, type) and not typing.get_args(tp) else str(tp)


def _coerce(value: Any, tp: Any, name: str, where: str) -> Any:
    """``value`` as type ``tp``; raises a ValueError naming the field and the source."""

    def bad() -> ValueError:
        return ValueError(f"{where}: {name} must be {_type_name(tp)}, got {value!r}")

    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        for option in options:  # the first type that takes the value
            try:
                return _coerce(value, option, name, where)
            except ValueError:
                pass
        raise bad()
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise bad()
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise bad()
        try:
            return float(value)
        except ValueError:
            raise bad() from None
    if tp is int:
        if isinstance(value, bool):
            raise bad()
        if isinstance(value, int):
            return value
        try:
            f = float(value) if isinstance(value, (float, str)) else None
        except ValueError:
            f = None
        if f is None or not f.is_integer():
            raise bad()
        return int(f)
    if tp is str:
        if isinstance(value, str):
            return value
        raise bad()
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise bad()
        if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
            return tuple(value)  # a fixed-length tuple: kept as given
        item = args[0] if args else Any
        out = [_coerce(v, item, f"{name}[{i}]", where) for i, v in enumerate(value)]
        return out if origin is list else tuple(out)
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise bad()
        return value
    return value
