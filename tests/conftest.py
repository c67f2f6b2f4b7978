import os

import numpy as np
import pytest

from pwf_dask.backend import cupy_or_none, default_fft_workers

# pytest-xdist runs one test process per core: each asking its FFT library (MKL's OpenMP teams
# above all) for every core oversubscribes them, which made the suite 30 % slower than one
# thread each (session 41: 13:18 against 10:26); a user's setting is kept
_XDIST_PROCESSES = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
if _XDIST_PROCESSES > 1:
    os.environ.setdefault("PWF_DASK_FFT_WORKERS", str(max(1, default_fft_workers() // _XDIST_PROCESSES)))


def pytest_configure(config):
    """Keep the module order :func:`pytest_collection_modifyitems` sets: xdist's loadscope
    would reorder the modules by their number of tests, which says little of their time."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(session, config, items):
    """Modules with the most slow tests first, then by their number of tests; each module's
    own order kept. Loadscope hands a worker the next module as it runs dry, so the long
    modules should start first, and the short ones fill in at the end (longest first): on
    session 55's test times the two workers' shares were 777 / 721 s in xdist's order by
    number of tests, 749 / 749 s in this one."""
    modules: dict[str, list] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::")[0], []).append(item)

    def weight(tests: list) -> tuple[int, int]:
        return (-sum(t.get_closest_marker("slow") is not None for t in tests), -len(tests))

    items[:] = [t for tests in sorted(modules.values(), key=weight) for t in tests]


@pytest.fixture(autouse=True)
def pwf_dask_messages():
    """The library's stage messages and progress on stderr, as the CLI shows them (tests read
    them with capsys), whatever an earlier test's `-q` left."""
    from pwf_dask.log import configure

    configure(0)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def small_scene():
    """The paper's geometry and diffuser (P3000) at 256^2, 1e4 photons a pixel, seed 1: the
    retrieval and detector tests' common scene, simulated once per test process."""
    from pwf_dask.simulation import SpeckleSetup, simulate_projection

    return simulate_projection(SpeckleSetup(shape=(256, 256), photons=1e4), seed=1)


@pytest.fixture(scope="session")
def small_scene_result(small_scene):
    """``small_scene`` retrieved with every default, for the tests that hold it beside another
    retrieval (one default retrieval at 256^2 is ~10 s of the suite's time)."""
    from pwf_dask import retrieve_projection

    sim = small_scene
    return retrieve_projection(sim.sample, sim.reference, **sim.geometry())


@pytest.fixture(params=["device", "emulated"])
def cupy(request):
    """CuPy on a CUDA device (skipped without one), and the CPU emulator of
    ``tests/emulated_cupy.py``, which runs the same CuPy code paths on any machine and is
    as strict as CuPy about host arrays reaching device code."""
    if request.param == "device":
        cp = cupy_or_none()
        if cp is None:
            pytest.skip("CuPy with a CUDA device is not available")
        yield cp
        return
    from emulated_cupy import installed

    from pwf_dask.pipeline import workflow

    with installed() as cp:
        yield cp
    workflow._DIFFUSERS.clear()  # fits made of emulated arrays must not reach a real device run
