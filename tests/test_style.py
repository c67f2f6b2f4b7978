"""The code stays ruff-clean (skipped where ruff is not installed), and the documentation's
relative links lead somewhere."""

import re
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


def test_documentation_links_resolve():
    """Every relative link of README.md, docs/ and the committed results names a file that
    exists, relative to the page that holds it (as GitHub and any Markdown viewer read it)."""
    root = Path(__file__).parents[1]
    pages = [root / "README.md", *sorted((root / "docs").glob("*.md")), *sorted(root.glob("*/results/*.md"))]
    broken = []
    for page in pages:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" not in target and not (page.parent / target).exists():
                broken.append(f"{page.relative_to(root)} -> {target}")
    assert not broken, broken
