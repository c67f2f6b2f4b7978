import numpy as np
import pytest

from pwf_dask.backend import cupy_or_none


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def cupy():
    cp = cupy_or_none()
    if cp is None:
        pytest.skip("CuPy with a CUDA device is not available")
    return cp
