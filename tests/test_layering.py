"""The house's layering (docs/architecture.md, "Layers"): every import inside the
package, at module level or inside a function, goes down or sideways, never up.

From the bottom: the shared helpers; the robot description (plain data); the
algorithms (estimation, identification, control), which serve any robot from a
MultibodyPlant and names; the robot (simulated, or over LCM); the closed-loop assembly;
the any-robot tools; the paper on HRP-2 and, on its floor, the experiments of any
robot (the balance experiment); the commands, one module a command, which import no
other command; the command line, which only dispatches to the commands.
"""

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "hrp2_drake"

HELPERS = {
    "config",
    "multibody",
    "console",
    "simulation",
    "step",
    "chain",
    "report",
    "kernels",
}
ALGORITHMS = {"estimation", "identification", "control"}
ROBOT = {"robot", "hardware"}

#: What each part of the package may import from the package (besides itself).
ALLOWED: dict[str, set[str]] = {
    "config": set(),
    "multibody": set(),
    "console": set(),
    "report": set(),
    "kernels": set(),
    "simulation": {"console"},
    "step": {"simulation", "console"},
    "chain": {"step", "simulation", "console"},
    "description": {"config", "multibody"},
    "estimation": HELPERS | {"description"},
    "identification": HELPERS | {"description", "estimation"},
    "control": HELPERS | {"description", "estimation", "identification"},
    "robot": HELPERS | {"description"} | ALGORITHMS,
    "hardware": HELPERS | {"description", "robot"} | ALGORITHMS,
    "assembly": HELPERS | {"description"} | ALGORITHMS | ROBOT,
    "tools": HELPERS | {"description", "assembly"} | ALGORITHMS | ROBOT,
    "paper": HELPERS | {"description", "assembly"} | ALGORITHMS | ROBOT,
    "experiments": HELPERS | {"description", "assembly"} | ALGORITHMS | ROBOT,
    "commands": HELPERS
    | {"description", "assembly", "tools", "paper", "experiments"}
    | ALGORITHMS
    | ROBOT,
    "cli": {"commands", "config", "console"},
}

#: The module of `commands/` that every command may import: what they share.
COMMANDS_SHARED = "options"


def _part(path: Path) -> str:
    """The part of the package a file belongs to: its folder, or its module's name
    for a module at the top of the package."""
    relative = path.relative_to(PACKAGE)
    return relative.parts[0] if len(relative.parts) > 1 else relative.stem


def _imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in `path`, at module level or inside a
    function; `from package import name` gives package and package.name (a module,
    or a name of package)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
            found += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return found


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, imported part of the package) of every import of the package in `path`."""
    found = []
    for line, module in _imported_modules(path):
        parts = module.split(".")
        if parts[0] == "hrp2_drake" and len(parts) > 1:
            found.append((line, parts[1]))
    return sorted(set(found))


def _sources() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if p != PACKAGE / "__init__.py")


def test_every_part_of_the_package_has_a_layer():
    parts = {_part(path) for path in _sources()}
    assert parts <= set(ALLOWED), f"no layer for {sorted(parts - set(ALLOWED))}"


@pytest.mark.parametrize("path", _sources(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_down(path):
    part = _part(path)
    wrong = [
        f"{path.relative_to(PACKAGE.parent)}:{line} imports hrp2_drake.{target}"
        for line, target in _imports(path)
        if target != part and target not in ALLOWED.get(part, set())
    ]
    assert not wrong, f"{part} may import only {sorted(ALLOWED[part])}:\n" + "\n".join(
        wrong
    )


def test_the_rules_of_issue_19_are_in_the_table():
    """The three rules the layering must enforce, read from the table itself."""
    assert all(
        "paper" not in allowed
        for part, allowed in ALLOWED.items()
        if part not in ("commands", "cli")
    )
    assert ALLOWED["description"] <= {"config", "multibody"}
    # The experiments stand on the paper's floor: only the commands run them, and
    # neither they nor the paper import a command's pipeline (issue 37).
    assert [p for p, allowed in ALLOWED.items() if "experiments" in allowed] == [
        "commands"
    ]
    assert not (ALLOWED["paper"] | ALLOWED["experiments"]) & {"tools"}
    for part in ALGORITHMS:
        assert not ALLOWED[part] & {"robot", "hardware", "assembly", "tools", "paper"}


def test_the_checker_sees_an_upward_import(tmp_path, monkeypatch):
    """An import from inside a function is seen, and one going up is refused."""
    bad = tmp_path / "hrp2_drake" / "control" / "bad.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("def f():\n    from hrp2_drake.paper import hrp2\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "hrp2_drake")
    assert _imports(bad) == [(2, "paper")]
    with pytest.raises(
        AssertionError, match="control/bad.py:2 imports hrp2_drake.paper"
    ):
        test_imports_go_down(bad)


def test_only_the_command_line_imports_the_commands():
    """Issue 37: the commands are the top of the house; `cli.py` dispatches to them
    and imports nothing else of the package but the console and the config."""
    assert [part for part, allowed in ALLOWED.items() if "commands" in allowed] == [
        "cli"
    ]
    assert ALLOWED["cli"] == {"commands", "config", "console"}


def _command_imports(path: Path) -> list[tuple[int, str]]:
    """(line, name) of every import of a module of `commands/` in `path`."""
    return sorted(
        {
            (line, module.split(".")[2])
            for line, module in _imported_modules(path)
            if module.startswith("hrp2_drake.commands.") and len(module.split(".")) == 3
        }
    )


def _commands() -> list[Path]:
    return sorted(
        p
        for p in (PACKAGE / "commands").glob("*.py")
        if p.stem not in ("__init__", COMMANDS_SHARED)
    )


@pytest.mark.parametrize("path", _commands(), ids=lambda p: p.stem)
def test_a_command_imports_no_other_command(path):
    """Each command is one module that registers its parser and runs it (issue 37):
    it imports what the commands share (`commands/options.py`), never another
    command; the pipeline two commands run lives below, in its layer."""
    wrong = [
        f"{path.relative_to(PACKAGE.parent)}:{line} imports hrp2_drake.commands.{name}"
        for line, name in _command_imports(path)
        if name != COMMANDS_SHARED
    ]
    assert not wrong, "\n".join(wrong)


def test_the_command_check_sees_one(tmp_path):
    module = tmp_path / "bad.py"
    module.write_text(
        "from hrp2_drake.commands import identify, options\n"
        "def run():\n    from hrp2_drake.commands.track import run\n"
    )
    assert _command_imports(module) == [(1, "identify"), (1, "options"), (3, "track")]


def _private_imports(path: Path) -> list[str]:
    """`module.name` of every private name (a leading underscore) that `path` imports
    from another module of the package."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(
            "hrp2_drake"
        ):
            found += [
                f"{node.module}.{alias.name}"
                for alias in node.names
                if alias.name.startswith("_")
            ]
    return found


def test_no_module_imports_another_modules_private_names():
    """A name another module needs is public (issue 34): e.g. the balance builder
    wires the torque chain with the builders' public helpers."""
    found = {
        str(path.relative_to(PACKAGE)): names
        for path in _sources()
        if (names := _private_imports(path))
    }
    assert found == {}


def test_the_private_import_check_sees_one(tmp_path):
    module = tmp_path / "module.py"
    module.write_text("from hrp2_drake.assembly.builders import _hidden\n")
    assert _private_imports(module) == ["hrp2_drake.assembly.builders._hidden"]


def _tools_imports(path: Path) -> set[str]:
    """The modules of tools/ that `path` imports (their stems)."""
    return {
        module.split(".")[2]
        for _, module in _imported_modules(path)
        if module.startswith("hrp2_drake.tools.") and len(module.split(".")) >= 3
    }


def test_a_pipeline_imports_no_other_commands_pipeline():
    """Issue 37: tools/ holds the commands' pipelines, one a command; what two of
    them share lives below, in its layer (the logs' reading and the identification's
    report in identification/, the identification on a collection in assembly/,
    ground truth in robot/). The paper and the experiments import no pipeline at all
    (the table)."""
    found = {
        f"{path.relative_to(PACKAGE)} -> tools/{name}.py"
        for path in _sources()
        if _part(path) == "tools"
        for name in _tools_imports(path)
        if name != path.stem
    }
    assert sorted(found) == []


def test_the_pipeline_check_sees_one(tmp_path):
    module = tmp_path / "bad.py"
    module.write_text(
        "from hrp2_drake.tools import ground_truth\n"
        "def f():\n    from hrp2_drake.tools.track import TrackConfig\n"
    )
    assert _tools_imports(module) == {"ground_truth", "track"}
