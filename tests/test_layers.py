"""The house's layering (docs/design.md): numerics never see Dask or a store; only the pipeline sees Dask."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).parents[1] / "pwf_dask"

#: numerics: pure functions on NumPy or CuPy arrays
NUMERICS = (
    "backend",
    "physics",
    "calibration",
    "pwf",
    "baselines",
    "tomo",
    "retrieval",
    "options",
    "simulation/phantoms",
    "simulation/speckle",
)
STORAGE_AND_DASK = {"dask", "distributed", "dask_cuda", "dask_jobqueue", "zarr", "xarray", "matplotlib"}
OUTER_LAYERS = {"stores", "pipeline", "cli", "plots", "bench", "stability", "simulation.scan"}


def imports(path: Path) -> set[str]:
    """Every module a file imports, at its top or inside a function."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found |= {f"{node.module}.{a.name}" for a in node.names}
    return found


def files(part: str) -> list[Path]:
    p = PACKAGE / part
    return sorted(p.rglob("*.py")) if p.is_dir() else [p.with_suffix(".py")]


def internal(mods: set[str]) -> set[str]:
    return {m.removeprefix("pwf_dask.") for m in mods if m.startswith("pwf_dask.")}


@pytest.mark.parametrize("part", NUMERICS)
def test_numerics_import_neither_dask_nor_stores(part):
    for path in files(part):
        mods = imports(path)
        assert not {m.split(".")[0] for m in mods} & STORAGE_AND_DASK, path
        leaks = {m for m in internal(mods) if any(m == o or m.startswith(o + ".") for o in OUTER_LAYERS)}
        assert not leaks, f"{path} imports {leaks}"


def test_only_the_pipeline_imports_dask():
    for path in sorted(PACKAGE.rglob("*.py")):
        if "pipeline" in path.parts:
            continue
        dask = {m for m in imports(path) if m.split(".")[0] in {"dask", "distributed", "dask_cuda", "dask_jobqueue"}}
        assert not dask, f"{path} imports {dask}"


def test_stores_do_not_depend_on_the_algorithms():
    for path in files("stores"):
        leaks = {
            m
            for m in internal(imports(path))
            if m.split(".")[0] in {"retrieval", "pwf", "calibration", "baselines", "pipeline", "tomo"}
        }
        assert not leaks, f"{path} imports {leaks}"
