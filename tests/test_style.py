"""Lint and format (ruff, configured in pyproject.toml) hold for the whole tree, so CI checks them."""

import shutil
import subprocess

import pytest

from hron_jax.paths import REPO_ROOT


@pytest.mark.parametrize('args', [['check', '.'], ['format', '--check', '.']], ids=['lint', 'format'])
def test_ruff(args):
    ruff = shutil.which('ruff') or pytest.skip('ruff is not installed (pip install -e ".[test]")')
    r = subprocess.run([ruff, *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, (
        f'ruff {" ".join(args)} (fix with `ruff check --fix . && ruff format .`):\n'
        + (r.stdout + r.stderr)[-3000:]
    )
