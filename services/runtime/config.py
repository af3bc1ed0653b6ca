"""YAML configuration files loaded into typed structs: documented defaults, and errors that name the bad key.

A service declares its config as a ``msgspec.Struct`` (with ``forbid_unknown_fields=True``) and reads YAML with
:func:`load_config` (a file), :func:`config_from_text` or :func:`config_from_mapping`: missing keys take their
defaults; unknown keys, wrong types and out-of-range values raise a :class:`ConfigError` naming the key path.
"""
from __future__ import annotations

import difflib
import math
import os
import re
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import msgspec.inspect
import yaml

from protocol.messages import validation_error_path

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration that cannot be used. ``key`` is the dotted path of the offending key."""

    def __init__(self, source: str, reason: str, key: str = "") -> None:
        self.source = source
        self.reason = reason
        self.key = key
        where = f", key '{key}'" if key else ""
        super().__init__(f"{source}{where}: {reason}")


class ConfigStruct(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """Base for config sections."""


def _parse_yaml(text: str, name: str) -> Any:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(name, f"not valid YAML ({exc})") from None
    return {} if data is None else data


def read_yaml(path: str | os.PathLike) -> Any:
    """The parsed YAML document of a file (an empty document is an empty mapping)."""
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise ConfigError(str(path), f"cannot read ({exc.strerror or exc})") from None
    return _parse_yaml(text, str(path))


def load_config(path: str | os.PathLike | None, config_type: type[T], section: str | None = None) -> T:
    """Load ``config_type`` from a YAML file (None: all defaults). With ``section``, only that top-level key of
    the document is used (a missing section means defaults)."""
    if path is None:
        return config_from_mapping({}, config_type, "<defaults>")
    return config_from_mapping(read_yaml(path), config_type, str(path), section)


def config_from_text(text: str, config_type: type[T], section: str | None = None, name: str = "<text>") -> T:
    return config_from_mapping(_parse_yaml(text, name), config_type, name, section)


def config_from_mapping(data: Any, config_type: type[T], name: str = "<mapping>", section: str | None = None) -> T:
    if not isinstance(data, dict):
        raise ConfigError(name, f"expected a mapping at the top level, got {type(data).__name__}")
    if section is not None:
        data = data.get(section) or {}
    try:
        return msgspec.convert(data, config_type, strict=False)
    except msgspec.ValidationError as exc:
        path, reason = validation_error_path(exc)
        reason += _did_you_mean(config_type, path, reason)
        if section:
            path = f"{section}.{path}" if path else section
        raise ConfigError(name, reason, path) from None


def _did_you_mean(config_type: type, path: str, reason: str) -> str:
    """For an unknown key, the closest known key at that place (a mistyped key otherwise gets only a refusal)."""
    unknown = re.search(r"unknown field `([^`]+)`", reason)
    if unknown is None:
        return ""
    info = msgspec.inspect.type_info(config_type)
    for part in path.split(".")[:-1]:
        info = _struct_of(info)
        field = next((f for f in info.fields if f.encode_name == part), None) if info is not None else None
        if field is None:
            return ""
        info = field.type
    info = _struct_of(info)
    names = [f.encode_name for f in info.fields] if info is not None else []
    close = difflib.get_close_matches(unknown.group(1), names, n=1)
    return f" (did you mean `{close[0]}`?)" if close else ""


def _struct_of(info):
    """The struct type behind an Optional (or any union holding one struct), or None."""
    if isinstance(info, msgspec.inspect.StructType):
        return info
    if isinstance(info, msgspec.inspect.UnionType):
        return next((t for t in info.types if isinstance(t, msgspec.inspect.StructType)), None)
    return None


def apply_override(data: dict, assignment: str, name: str = "--set") -> None:
    """Apply one ``dotted.key=value`` assignment (the value is read as YAML) to a config mapping in place, so that
    a deploy profile can change one key of a shipped config file without copying it."""
    key, sep, text = assignment.partition("=")
    if not sep or not key.strip():
        raise ConfigError(name, f"{assignment!r} is not key=value")
    parts = key.strip().split(".")
    node = data
    for i, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(name, "is not a mapping", ".".join(parts[:i + 1]))
        node = child
    try:
        node[parts[-1]] = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(name, f"value of {key.strip()} is not valid YAML ({exc})") from None


def config_mapping(path: str | os.PathLike | None, assignments=(), name: str = "--set") -> dict:
    """A config file's mapping (empty without a file) with ``dotted.key=value`` overrides applied: what a service
    validates at start (``--config FILE --set ...``), and what a launcher reads of a service it starts."""
    data = read_yaml(path) if path else {}
    if not isinstance(data, dict):
        raise ConfigError(str(path), "expected a mapping at the top level")
    for assignment in assignments:
        apply_override(data, assignment, name)
    return data


def dump_defaults(config_type: type) -> str:
    """YAML text of a config type's defaults (for documentation and `--print-config`)."""
    return yaml.safe_dump(msgspec.to_builtins(config_type()), sort_keys=False)
