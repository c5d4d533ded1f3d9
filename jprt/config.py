"""Configs: plain nested dicts with typed ``--set a.b=value`` overrides, strict keys, stable hashes.

Every experiment defines ``CONFIG`` (the defaults). Overrides are deep-merged into a copy; a key
that the defaults do not have is an error naming the closest valid key (never silently added),
and a value must have a type compatible with the default's (int -> float widening is allowed,
``None`` defaults accept anything). A section with a ``name`` key (a scene, a model) that is set
to a different name is replaced whole, since its keys belong to the new name. The hash of a resolved config is stable across processes
and dict orders, and is written next to every result with the config itself.
"""

from __future__ import annotations

import ast
import copy
import difflib
import json
import os
from typing import Any, Iterable, Mapping

from jprt.hashing import array_digest, config_hash, stable_hash

__all__ = [
    "ConfigError",
    "parse_value",
    "parse_override",
    "flatten",
    "merge",
    "apply_overrides",
    "config_hash",
    "stable_hash",
    "array_digest",
    "section_defaults",
    "section_from_string",
    "save_resolved",
]


class ConfigError(ValueError):
    """A config override names an unknown key or has an incompatible type."""


def parse_value(text: str) -> Any:
    """Parse a command-line value: Python/JSON literals (ints, floats, bools, None, lists,
    dicts, quoted strings), ``true``/``false``/``null``; anything else stays a string."""
    lowered = text.strip().lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    if lowered in ("none", "null"):
        return None
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        pass
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_override(item: str) -> tuple[str, Any]:
    """``"a.b=value"`` -> ("a.b", parsed value)."""
    if "=" not in item:
        raise ConfigError(f"override {item!r} is not of the form key.path=value")
    key, text = item.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise ConfigError(f"override {item!r} has an empty key")
    return key, parse_value(text)


def flatten(config: Mapping, prefix: str = "") -> dict[str, Any]:
    """All dotted key paths of a nested dict (interior dicts included) -> values."""
    out: dict[str, Any] = {}
    for k, v in config.items():
        path = f"{prefix}{k}"
        out[path] = v
        if isinstance(v, Mapping):
            out.update(flatten(v, path + "."))
    return out


def _closest(key: str, candidates: Iterable[str]) -> str:
    candidates = list(candidates)
    match = difflib.get_close_matches(key, candidates, n=1, cutoff=0.0)
    return match[0] if match else "(none)"


def _coerce(path: str, default: Any, value: Any) -> Any:
    if default is None or value is None:
        return value
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
    elif isinstance(default, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif isinstance(default, float):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif isinstance(default, str):
        if isinstance(value, str):
            return value
    elif isinstance(default, (list, tuple)):
        if isinstance(value, (list, tuple)):
            return type(default)(value)
    elif isinstance(default, Mapping):
        if isinstance(value, Mapping):
            return value
    else:
        return value
    raise ConfigError(
        f"config key {path!r} expects {type(default).__name__} (default {default!r}), got {type(value).__name__} {value!r}"
    )


def merge(base: Mapping, overrides: Mapping, *, _prefix: str = "") -> dict:
    """Deep-merge ``overrides`` into a copy of ``base``; unknown keys raise ConfigError."""
    out = copy.deepcopy(dict(base))
    for k, v in overrides.items():
        path = f"{_prefix}{k}"
        if k not in out:
            raise ConfigError(f"unknown config key {path!r}; did you mean {_prefix + _closest(k, list(out))!r}?")
        if (isinstance(out[k], Mapping) and isinstance(v, Mapping) and "name" in v
                and v["name"] != out[k].get("name")):
            out[k] = copy.deepcopy(dict(v))  # a named section switched to another name: its keys are the new ones
        elif isinstance(out[k], Mapping) and isinstance(v, Mapping) and out[k]:
            out[k] = merge(out[k], v, _prefix=path + ".")
        else:
            out[k] = _coerce(path, out[k], v)
    return out


def section_defaults(name: str) -> dict:
    """The config section of a scene of kind ``name`` with its defaults, what ``--set
    scene.name=NAME`` switches a config's scene section to (so the kind's own keys can follow:
    ``--set scene.name=xml --set scene.path=/abs/scene.xml``). Keys without a default (a file's
    path, a mesh, a layout) are empty and must be set."""
    sections = {
        "empty": {"name": "empty"},
        "cornell_box": {"name": "cornell_box", "area_light": True},
        "glossy_cornell": {"name": "glossy_cornell", "floor_roughness": 0.15, "sphere_roughness": 0.02},
        "xml": {"name": "xml", "path": "", "keep_emitters": True, "opening": ""},
        "asset_room": {"name": "asset_room", "mesh": "", "albedo": [0.75, 0.6, 0.45], "margin": 1.0, "size": 3.0,
                       "walls": True},
        "blocks": {"name": "blocks", "layout": {}, "size": 1.0},
    }
    if name not in sections:
        raise ValueError(f"unknown scene name {name!r}: use one of {sorted(sections)}")
    return copy.deepcopy(sections[name])


def section_from_string(value: str) -> dict:
    """A scene config section from a string: a scene name (``section_defaults``) or the path of a
    Mitsuba .xml file (``--set scene=/abs/scene.xml``)."""
    if value.lower().endswith(".xml"):
        if not os.path.isfile(value):
            raise FileNotFoundError(f"scene file not found: {value}")
        return {"name": "xml", "path": os.path.abspath(value), "keep_emitters": True}
    return section_defaults(value)


def _named_section(section: str, value: Any, current: Any) -> Any:
    """A named section's new value from ``--set``: for a scene section (a key called ``scene``), a
    string is a scene name or an .xml path (``section_from_string``), and a new ``name`` brings
    that kind's keys with their defaults (``section_defaults``)."""
    if section.split(".")[-1] != "scene" or not isinstance(current, Mapping):
        return value
    try:
        if isinstance(value, str):
            return section_from_string(value)
        if isinstance(value, Mapping) and "name" in value and value["name"] != current.get("name"):
            return {**section_defaults(str(value["name"])), **value}
    except (ValueError, FileNotFoundError) as e:
        raise ConfigError(f"{section}: {e}") from None
    return value


def apply_overrides(config: Mapping, items: Iterable[str]) -> dict:
    """Apply ``--set`` style items (``"a.b=value"``) in order to a copy of ``config``. A scene
    section takes a name or an .xml path as a string (``--set dataset.scene=/abs/room.xml``), and
    switching its ``name`` makes that kind's keys valid for the items after it
    (``--set scene.name=xml --set scene.path=/abs/room.xml``)."""
    out = copy.deepcopy(dict(config))
    for item in items:
        valid = flatten(out)  # a switched scene section brings its own keys
        key, value = parse_override(item)
        parts = key.split(".")
        if key not in valid and len(parts) > 1 and parts[-2] == "scene" and isinstance(valid.get(".".join(parts[:-1])),
                                                                                           Mapping):
            section = ".".join(parts[:-1])
            raise ConfigError(f"unknown config key {key!r} for a {valid[section].get('name')!r} scene; switch the "
                              f"scene's kind first (--set {section}.name=xml, or --set {section}=/abs/scene.xml)")
        if key not in valid:
            raise ConfigError(f"unknown config key {key!r}; did you mean {_closest(key, valid)!r}?")
        if parts[-1] == "name" and len(parts) > 1 and parts[-2] == "scene":  # scene.name=xml: the section switches kind
            section = ".".join(parts[:-1])
            key, value = section, _named_section(section, {"name": value}, valid[section])
        else:
            value = _named_section(key, value, valid[key])
        nested: dict = value
        for part in reversed(key.split(".")):
            nested = {part: nested}
        out = merge(out, nested)
    return out


def save_resolved(config: Mapping, folder: str) -> str:
    """Write ``config.json`` (the resolved config and its hash) into ``folder``; returns the hash."""
    from jprt.io import write_json

    digest = config_hash(config)
    write_json(os.path.join(folder, "config.json"), {"hash": digest, "config": config})
    return digest
