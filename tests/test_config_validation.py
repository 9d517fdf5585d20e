"""Configs are validated once, where they are loaded: `validate_config` runs the
config's own `validate()`, which must check every config nested in it; and a command
applies its options before that validation, never after it."""

import copy
import dataclasses
import importlib
import pkgutil

import pytest

import hrp2_drake
from hrp2_drake.config import _callable_without_arguments, nested_configs
from hrp2_drake.description import load_robot_description
from hrp2_drake.tools.record import RecordConfig


def _config_classes() -> list[type]:
    """Every config of hrp2_drake (a dataclass defined in it) with a `validate()`."""
    for info in pkgutil.walk_packages(hrp2_drake.__path__, "hrp2_drake."):
        importlib.import_module(info.name)
    found = {}
    for module in pkgutil.walk_packages(hrp2_drake.__path__, "hrp2_drake."):
        for value in vars(importlib.import_module(module.name)).values():
            if (
                isinstance(value, type)
                and dataclasses.is_dataclass(value)
                and value.__module__.startswith("hrp2_drake.")
                and callable(getattr(value, "validate", None))
            ):
                found[f"{value.__module__}.{value.__qualname__}"] = value
    return [found[name] for name in sorted(found)]


def _validated_below(config, path: str = "") -> list[tuple[str, object]]:
    """The configs nested in `config` that have a `validate()` of their own (through
    nested configs that have none)."""
    out = []
    for where, child in nested_configs(config, path):
        if _callable_without_arguments(getattr(child, "validate", None)):
            out.append((where, child))
        else:
            out += _validated_below(child, where)
    return out


#: Valid instances of the configs whose defaults are not (no robot name, no bus).
VALID = {
    "RobotDescription": lambda: copy.deepcopy(load_robot_description("hrp2")),
    "RecordConfig": lambda: RecordConfig(robot="xl330_pendulum"),
}


def _composite_defaults():
    """(class, default instance) of each config whose defaults nest validated
    configs."""
    out = []
    for schema in _config_classes():
        try:
            config = VALID.get(schema.__name__, schema)()
        except TypeError:  # needs arguments: not a config loaded from YAML
            continue
        if _callable_without_arguments(config.validate) and _validated_below(config):
            out.append(pytest.param(schema, config, id=schema.__name__))
    return out


@pytest.mark.parametrize("schema, config", _composite_defaults())
def test_a_config_validates_every_config_nested_in_it(monkeypatch, schema, config):
    nested = _validated_below(config)
    called = set()
    for _, child in nested:
        original = type(child).validate

        def record(self, *args, _original=original, **kwargs):
            called.add(id(self))
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(type(child), "validate", record)
    config.validate()
    missing = [where for where, child in nested if id(child) not in called]
    assert not missing, f"{schema.__name__}.validate() does not validate {missing}"
