"""The code's style is checked where the tests run: `ruff check` (the rules in
pyproject.toml's [tool.ruff]) and `ruff format --check` on the package, the scripts and
the tests. Fix with `ruff check --fix` and `ruff format`. And no function of the package
is over 80 lines (issue 37), but a numba kernel that says why it stays whole."""

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PLACES = ["hrp2_drake", "scripts", "tests"]
PACKAGE = REPO / "hrp2_drake"
MAX_LINES = 80
# A `@kernel` over MAX_LINES stays whole when the line just above its decorator says
# why, after this mark (one compiled pass per tick: a split costs calls).
WHOLE = "# Whole:"


def _ruff(*args: str) -> subprocess.CompletedProcess:
    ruff = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which(
        "ruff"
    )
    if ruff is None:
        pytest.fail("ruff is not installed: pip install -e '.[test]'")
    return subprocess.run(
        [ruff, *args, *PLACES], cwd=REPO, capture_output=True, text=True, timeout=300
    )


def test_ruff_check():
    result = _ruff("check", "--no-cache")
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


def test_ruff_format():
    result = _ruff("format", "--check", "--no-cache")
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


def _is_kernel(node: ast.FunctionDef) -> bool:
    """Decorated `@kernel` (or `@kernel(...)`, `@kernels.kernel`)."""
    for decorator in node.decorator_list:
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        name = getattr(target, "id", None) or getattr(target, "attr", None)
        if name == "kernel":
            return True
    return False


def _kept_whole(node: ast.FunctionDef, lines: list[str]) -> bool:
    """A kernel whose line above its decorators is `# Whole: <why>`."""
    first = min((d.lineno for d in node.decorator_list), default=node.lineno)
    above = lines[first - 2].strip() if first >= 2 else ""
    reason = above.removeprefix(WHOLE).strip()
    return _is_kernel(node) and above.startswith(WHOLE) and len(reason) >= 10


def _long_functions(package: Path) -> list[str]:
    """The functions and methods of `package` over MAX_LINES lines (from `def` to
    their last line), but the kernels kept whole, as `path:line name (n lines)`."""
    found = []
    for path in sorted(package.rglob("*.py")):
        text = path.read_text()
        lines = text.splitlines()
        for node in ast.walk(ast.parse(text, str(path))):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            length = node.end_lineno - node.lineno + 1
            if length > MAX_LINES and not _kept_whole(node, lines):
                where = path.relative_to(package.parent)
                found.append(f"{where}:{node.lineno} {node.name} ({length} lines)")
    return found


def test_functions_are_at_most_80_lines():
    long = _long_functions(PACKAGE)
    assert not long, (
        f"over {MAX_LINES} lines: split into helpers, or, for a numba kernel that a "
        f"split would slow, say why on the line above its decorator ('{WHOLE} ...'):"
        "\n" + "\n".join(long)
    )


def test_the_length_check_sees_a_long_function(tmp_path):
    package = tmp_path / "hrp2_drake"
    package.mkdir()
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_LINES))  # def + 80 lines
    at_most = "".join(f"    x{i} = {i}\n" for i in range(MAX_LINES - 1))
    (package / "long.py").write_text(
        "from hrp2_drake.kernels import kernel\n\n\n"
        f"def long():\n{body}\n\n"
        f"@kernel\ndef silent_kernel():\n{body}\n\n"
        f"{WHOLE} one compiled pass per tick; a split costs calls\n"
        f"@kernel\ndef kernel_kept_whole():\n{body}\n\n"
        f"{WHOLE} a plain function is no kernel\n"
        f"def not_a_kernel():\n{body}\n\n"
        f"class Step:\n    def step(self):\n{body.replace('    ', '        ')}\n\n"
        f"def at_most_80_lines():\n{at_most}"
    )
    found = sorted(entry.split()[1] for entry in _long_functions(package))
    assert found == ["long", "not_a_kernel", "silent_kernel", "step"]
