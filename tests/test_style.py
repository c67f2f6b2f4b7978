"""The code stays ruff-clean (skipped where ruff is not installed)."""

import shutil
import subprocess
from pathlib import Path

import pytest


def test_ruff_clean():
    ruff = shutil.which("ruff") or str(Path(__file__).parents[1] / ".venv" / "bin" / "ruff")
    if not Path(ruff).exists():
        pytest.skip("ruff not installed")
    root = Path(__file__).parents[1]
    out = subprocess.run(
        [ruff, "check", "pwf_dask", "benchmarks", "tests", "workflows", "deploy"],
        cwd=root,
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout
