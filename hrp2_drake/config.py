"""Loading typed configs: `pydrake.common.yaml.yaml_load_typed` plus clear errors.

Every config of hrp2_drake is a dataclass with typed defaults (next to the system that
reads it). `load_config` reads YAML into it and reports every problem as a one-line
ValueError that names the source file and the key's full path (e.g.
`sensors.accelerometer.stdd`): a YAML syntax error (with its line and column), a
duplicated key, an unknown key, a value of the wrong type; then `validate_config` runs
the config's `validate()`, once. A config is validated where it is loaded (a command:
once its options are applied) and not changed after; a config's `validate()` checks
every config nested in it (`nested_configs`), so that nothing is validated twice.

Note: modules that define config dataclasses must not use
`from __future__ import annotations` (yaml_load_typed needs real types), and
yaml_load_typed does not call `__post_init__`: validation lives in `validate()`.

A config's fields can be named by path ("controller.k6"): `field_at`, `set_field_at`,
`replace_fields` (`dataclasses.replace` by path) and `field_type`, for code that varies
settings by name.
"""

import copy
import dataclasses
import inspect
import math
import types
import typing
from collections.abc import Hashable
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydrake.common.yaml import yaml_load_typed

T = TypeVar("T")


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicated keys (PyYAML keeps the last one silently)
    and, like Drake's loader, accepts variant tags (`!Name {...}`)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, Hashable):
                continue  # SafeLoader reports it
            if key in seen:
                mark = key_node.start_mark
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicated key '{key}'", mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _variant(loader, tag, node):
    """A tagged node, as Drake reads it: a mapping gets its tag as key "_tag"."""
    if isinstance(node, yaml.MappingNode):
        return {**loader.construct_mapping(node), "_tag": tag}
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node)
    return loader.construct_scalar(node)


_StrictLoader.add_multi_constructor("", _variant)


def one_line(text: str) -> str:
    """`text` with its lines joined by "; " (error messages are printed on one line)."""
    return "; ".join(line.strip() for line in str(text).splitlines() if line.strip())


def read_yaml_text(filename: str | Path) -> str:
    """The text of a YAML file; a missing file, a folder or a binary file raise an
    error that names it."""
    path = Path(filename)
    if not path.exists():
        raise FileNotFoundError(f"{filename}: no such file")
    if path.is_dir():
        raise IsADirectoryError(f"{filename}: is a folder, expected a YAML file")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(
            f"{filename}: not a text (UTF-8) file, expected YAML"
        ) from None


def parse_yaml(text: str, source: str) -> Any:
    """The raw YAML data of `text` (None when empty); a syntax error or a duplicated key
    is a ValueError naming `source`, the line and the column."""
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = error.problem or error.context or "invalid YAML"
        raise ValueError(
            f"{source}: invalid YAML{where}: {one_line(problem)}"
        ) from None
    except yaml.YAMLError as error:
        raise ValueError(f"{source}: invalid YAML: {one_line(error)}") from None
    except RecursionError:  # PyYAML composes nested nodes recursively
        raise ValueError(
            f"{source}: invalid YAML: lists or mappings nested more deeply than the "
            "YAML reader can follow"
        ) from None


def _optional(schema: Any) -> Any:
    """X for Optional[X] (X | None), else `schema` itself."""
    args = [a for a in typing.get_args(schema) if a is not type(None)]
    if typing.get_origin(schema) in (typing.Union, types.UnionType) and len(args) == 1:
        return args[0]
    return schema


def moved_keys(**moved: str):
    """Class decorator of a config whose layout changed: each old key (a keyword) and
    the path it moved to, relative to the config (e.g. `k6="controller.k6"`).
    `load_config` refuses a file that still uses an old key, wherever the config is
    nested, with one line naming the new key."""

    def mark(schema: type[T]) -> type[T]:
        schema._moved_keys = dict(moved)
        return schema

    return mark


def _unknown_keys(
    schema: Any, data: Any, path: str
) -> list[tuple[str, list[str], tuple[str, str] | None]]:
    """(path, the keys known there, None) of each key in `data` that `schema` (a
    dataclass type) does not have; for a key that moved (`moved_keys`), (path, the keys
    known there, (the schema's name, where the key moved to))."""
    schema = _optional(schema)
    origin, args = typing.get_origin(schema), typing.get_args(schema)
    if origin is list and isinstance(data, list):
        return sum(
            (_unknown_keys(args[0], v, f"{path}[{i}]") for i, v in enumerate(data)), []
        )
    if origin is dict and isinstance(data, dict):
        return sum(
            (_unknown_keys(args[1], v, f"{path}.{k}") for k, v in data.items()), []
        )
    if not (dataclasses.is_dataclass(schema) and isinstance(data, dict)):
        return []
    hints = typing.get_type_hints(schema)
    out = []
    for key, value in data.items():
        where = f"{path}.{key}" if path else str(key)
        if key == "_tag":
            continue
        if key not in hints:
            moved = getattr(schema, "_moved_keys", {}).get(key)
            out.append((where, sorted(hints), moved and (schema.__name__, moved)))
        else:
            out += _unknown_keys(hints[key], value, where)
    return out


def _moved_keys_line(
    unknown: list[tuple[str, list[str], tuple[str, str] | None]],
) -> str:
    """The moved keys among `unknown` (`_unknown_keys`) on one line, by the config they
    are in (e.g. "torque_control: TorqueControlConfig: 'k6' moved to 'controller.k6'");
    "" if none moved."""
    groups: dict[str, list[str]] = {}
    for where, _, moved in unknown:
        if moved:
            parent, _, key = where.rpartition(".")
            head = f"{parent}: {moved[0]}" if parent else moved[0]
            groups.setdefault(head, []).append(f"'{key}' moved to '{moved[1]}'")
    return "; ".join(f"{head}: {', '.join(keys)}" for head, keys in groups.items())


def _describe(value: Any) -> str:
    """A YAML value as an error message shows it."""
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    return f"{type(value).__name__} {value!r}"


def _type_errors(schema: Any, value: Any, path: str) -> list[str]:
    """'<path>: expected ..., got ...' for the values of `value` whose YAML type does
    not fit `schema` (the checks yaml_load_typed makes, but naming the key)."""
    where = path or "the file"
    if value is None and _optional(schema) is not schema:
        return []
    schema = _optional(schema)
    origin, args = typing.get_origin(schema), typing.get_args(schema)
    if schema is float:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            return [f"{where}: expected a number, got {_describe(value)}"]
        if isinstance(value, str):
            try:
                float(value)
            except ValueError:
                return [f"{where}: expected a number, got {_describe(value)}"]
        return []
    if schema is int:
        if isinstance(value, bool) or not isinstance(value, int):
            return [f"{where}: expected an integer, got {_describe(value)}"]
        return []
    if schema is bool:
        return (
            []
            if isinstance(value, bool)
            else [f"{where}: expected true or false, got {_describe(value)}"]
        )
    if schema is str:
        return (
            []
            if isinstance(value, str)
            else [f"{where}: expected a string, got {_describe(value)}"]
        )
    if origin is list:
        if not isinstance(value, list):
            return [f"{where}: expected a list, got {_describe(value)}"]
        return sum(
            (_type_errors(args[0], v, f"{path}[{i}]") for i, v in enumerate(value)), []
        )
    if origin is dict:
        if not isinstance(value, dict):
            return [f"{where}: expected a mapping, got {_describe(value)}"]
        return sum(
            (_type_errors(args[1], v, f"{path}.{k}") for k, v in value.items()), []
        )
    if dataclasses.is_dataclass(schema):
        if not isinstance(value, dict):
            return [
                f"{where}: expected a mapping ({schema.__name__}), "
                f"got {_describe(value)}"
            ]
        hints = typing.get_type_hints(schema)
        out = []
        for key, item in value.items():
            if key in hints:
                out += _type_errors(
                    hints[key], item, f"{path}.{key}" if path else str(key)
                )
        return out
    return []  # Optional, Union, numpy arrays...: left to yaml_load_typed


def _callable_without_arguments(method) -> bool:
    try:
        parameters = inspect.signature(method).parameters.values()
    except (TypeError, ValueError):
        return False
    return all(
        p.default is not p.empty or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        for p in parameters
    )


def validate_config(config: Any, source: str | None = None, path: str = "") -> None:
    """Validates a config once, where it is loaded (`load_config`, or a command once
    its options are applied): its `validate()`, which validates every config nested
    in it (`nested_configs`: a config's `validate()` is complete, a test holds every
    config to it); a config without a `validate()` of its own, that of each config
    nested in it (fields, list items, dict values). Nothing is checked only once a
    simulation runs, and nothing twice.

    Raises:
        ValueError: the first problem found, prefixed with `source` (a file) and the
            path of the nested config that found it (e.g. `station.sensors`).
    """
    validate = getattr(config, "validate", None)
    if validate is not None and _callable_without_arguments(validate):
        try:
            validate()
        except (ValueError, KeyError) as error:
            message = (
                error.args[0] if isinstance(error, KeyError) and error.args else error
            )
            prefix = "".join(f"{p}: " for p in (source, path) if p)
            if not prefix:
                raise
            raise ValueError(f"{prefix}{message}") from error
        return
    for child_path, child in nested_configs(config, path):
        validate_config(child, source, child_path)


def nested_configs(config: Any, path: str = "") -> list[tuple[str, Any]]:
    """(path, config) of each config (dataclass) nested in `config`: its fields, the
    items of its lists and the values of its dicts that are dataclasses."""
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        return []
    out = []
    for item in dataclasses.fields(config):
        value = getattr(config, item.name)
        where = f"{path}.{item.name}" if path else item.name
        children = []
        if dataclasses.is_dataclass(value):
            children = [(where, value)]
        elif isinstance(value, dict):
            children = [(f"{where}.{k}", v) for k, v in value.items()]
        elif isinstance(value, list):
            children = [(f"{where}[{i}]", v) for i, v in enumerate(value)]
        out += [(p, c) for p, c in children if dataclasses.is_dataclass(c)]
    return out


def field_at(config: Any, path: str) -> Any:
    """The value of the field at `path` of a config: "start_time", or a nested one
    ("controller.k6")."""
    for name in path.split("."):
        config = getattr(config, name)
    return config


def set_field_at(config: Any, path: str, value: Any) -> None:
    """Sets the field at `path` (as `field_at`) of `config`, in place."""
    parent, _, name = path.rpartition(".")
    setattr(field_at(config, parent) if parent else config, name, value)


def replace_fields(config: T, changes: dict[str, Any]) -> T:
    """`dataclasses.replace` by field path (as `field_at`): a copy of `config` with
    `changes`, the nested settings they touch copied too, the others shared."""
    top, nested = {}, {}
    for path, value in changes.items():
        name, _, rest = path.partition(".")
        if rest:
            nested.setdefault(name, {})[rest] = value
        else:
            top[name] = value
    for name, inner in nested.items():
        top[name] = replace_fields(top.get(name, getattr(config, name)), inner)
    return dataclasses.replace(config, **top)


def field_type(schema: type, path: str) -> Any:
    """The type of the field at `path` (as `field_at`) of the dataclass `schema`;
    None if it has no such field."""
    for name in path.split("."):
        hints = (
            typing.get_type_hints(schema) if dataclasses.is_dataclass(schema) else {}
        )
        if name not in hints:
            return None
        schema = hints[name]
    return schema


def check_finite(
    value: float, name: str, low: float | None = None, strict: bool = True
):
    """Raises ValueError naming `name` unless `value` is a finite number (and > low,
    or >= low when not strict)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number, got {value}")
    if low is not None and not (number > low if strict else number >= low):
        raise ValueError(
            f"{name} must be {'>' if strict else '>='} {low:g}, got {value}"
        )


def load_config(
    schema: type[T],
    filename: str | Path | None = None,
    data: str | None = None,
    defaults: T | None = None,
    validate: bool = True,
) -> T:
    """Reads a YAML file (or string) into the dataclass `schema` and validates it.

    Args:
        schema: the config dataclass.
        filename: a YAML file; or
        data: YAML text.
        defaults: values for the keys the YAML leaves out (default: `schema()`).
        validate: run `validate_config` (False: the caller changes the config first,
            e.g. from command-line options, then calls `validate_config` with
            `filename` as the source).

    Raises:
        FileNotFoundError, IsADirectoryError: `filename` is not a file.
        ValueError: a syntax error, a duplicated or unknown key, a wrong type (each
            with its path and the source), or what the configs' `validate()` find
            wrong.
    """
    if (filename is None) == (data is None):
        raise ValueError("load_config: give exactly one of filename or data")
    source = str(filename) if filename is not None else "<yaml text>"
    text = read_yaml_text(filename) if filename is not None else data
    raw = parse_yaml(text, source)
    if isinstance(raw, dict):  # Drake drops root keys starting with "_" (templates)
        raw = {k: v for k, v in raw.items() if not str(k).startswith("_")}
    if raw is not None and not isinstance(raw, dict):
        raise ValueError(
            f"{source}: expected a mapping of {schema.__name__} keys, "
            f"got {_describe(raw)}"
        )
    unknown = _unknown_keys(schema, raw or {}, "")
    moved = _moved_keys_line(unknown)
    if moved:
        raise ValueError(f"{source}: {moved}")
    if unknown:
        where, known, _ = unknown[0]
        there = f" in {where.rpartition('.')[0]}" if "." in where else ""
        raise ValueError(
            f"{source}: unknown key(s) {[path for path, _, _ in unknown]} for "
            f"{schema.__name__} (known{there}: {known})"
        )
    wrong = _type_errors(schema, raw or {}, "")
    if wrong:
        raise ValueError(f"{source}: {'; '.join(wrong)}")
    config = copy.deepcopy(defaults) if defaults is not None else schema()
    if raw:
        try:
            config = yaml_load_typed(schema=schema, data=text, defaults=config)
        except (
            RuntimeError,
            ValueError,
            TypeError,
            AssertionError,
            yaml.YAMLError,
        ) as error:
            raise ValueError(f"{source}: {one_line(error)}") from error
    if validate:
        validate_config(config, source if filename is not None else None)
    return config
