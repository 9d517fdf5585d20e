"""Loading typed configs: `pydrake.common.yaml.yaml_load_typed` plus clear errors.

Every config of hrp2_drake is a dataclass with typed defaults (next to the system that
reads it). `load_config` reads YAML into it and reports an unknown key with its full
path (e.g. `sensors.accelerometer.stdd`), then runs the config's `validate()`.

Note: modules that define config dataclasses must not use
`from __future__ import annotations` (yaml_load_typed needs real types), and
yaml_load_typed does not call `__post_init__`: validation lives in `validate()`.
"""

import dataclasses
import typing
from pathlib import Path
from typing import Any, TypeVar

from pydrake.common.yaml import yaml_load, yaml_load_typed

T = TypeVar("T")


def _unknown_keys(schema: Any, data: Any, path: str) -> list[str]:
    """Paths of keys in `data` that `schema` (a dataclass type) does not have."""
    if not (dataclasses.is_dataclass(schema) and isinstance(data, dict)):
        return []
    hints = typing.get_type_hints(schema)
    out = []
    for key, value in data.items():
        where = f"{path}.{key}" if path else key
        if key not in hints:
            out.append(where)
            continue
        field_type = hints[key]
        if typing.get_origin(field_type) is dict:
            value_type = typing.get_args(field_type)[1]
            if isinstance(value, dict):
                for name, item in value.items():
                    out += _unknown_keys(value_type, item, f"{where}.{name}")
        else:
            out += _unknown_keys(field_type, value, where)
    return out


def load_config(
    schema: type[T],
    filename: str | Path | None = None,
    data: str | None = None,
    defaults: T | None = None,
) -> T:
    """Reads a YAML file (or string) into the dataclass `schema` and validates it.

    Args:
        schema: the config dataclass.
        filename: a YAML file; or
        data: YAML text.
        defaults: values for the keys the YAML leaves out (default: `schema()`).

    Raises:
        ValueError: an unknown key (with its path and the source), or what the
            config's `validate()` finds wrong.
    """
    if (filename is None) == (data is None):
        raise ValueError("load_config: give exactly one of filename or data")
    source = str(filename) if filename is not None else "<yaml text>"
    raw = yaml_load(filename=str(filename)) if filename is not None else yaml_load(data=data)
    unknown = _unknown_keys(schema, raw or {}, "")
    if unknown:
        raise ValueError(
            f"{source}: unknown key(s) {unknown} for {schema.__name__} "
            f"(known: {sorted(typing.get_type_hints(schema))})"
        )
    kwargs = dict(schema=schema, defaults=defaults if defaults is not None else schema())
    try:
        if filename is not None:
            config = yaml_load_typed(filename=str(filename), **kwargs)
        else:
            config = yaml_load_typed(data=data, **kwargs)
    except RuntimeError as error:
        raise ValueError(f"{source}: {error}") from error
    if hasattr(config, "validate"):
        config.validate()
    return config
