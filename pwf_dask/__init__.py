"""pwf-dask: single-shot speckle-based X-ray phase microtomography by preconditioned Wirtinger flow."""

from importlib.metadata import PackageNotFoundError, version

from pwf_dask.options import RetrievalOptions
from pwf_dask.retrieval import RetrievalResult, retrieve_projection

try:
    __version__ = version("pwf-dask")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.1.0"

__all__ = ["RetrievalOptions", "RetrievalResult", "retrieve_projection", "__version__"]
