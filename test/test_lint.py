"""Lint: `ruff check` (ruff.toml: pycodestyle, pyflakes, import order, 120 columns) passes on the whole
tree, and the whole tree is formatted as `ruff format` writes it."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FORMATTED = ['.']


def ruff() -> list[str]:
    exe = Path(sys.executable).parent / 'ruff'
    if exe.exists():
        return [str(exe)]
    if shutil.which('ruff'):
        return [shutil.which('ruff')]
    pytest.skip('ruff is not installed (requirements.txt lists it; bash scripts/setup.sh installs it)')


def test_ruff_check_passes_on_the_tree():
    out = subprocess.run([*ruff(), 'check', '--no-cache', '.'], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_tree_is_ruff_formatted():
    out = subprocess.run(
        [*ruff(), 'format', '--check', '--no-cache', '--diff', *FORMATTED], cwd=REPO, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr
