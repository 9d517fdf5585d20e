"""The code's style is checked where the tests run: `ruff check` (the rules in
pyproject.toml's [tool.ruff]) and `ruff format --check` on the package, the scripts and
the tests. Fix with `ruff check --fix` and `ruff format`."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PLACES = ["hrp2_drake", "scripts", "tests"]


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
