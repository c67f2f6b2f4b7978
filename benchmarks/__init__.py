"""Benchmarks and studies of pwf-dask, out of the package: speed, accuracy, where each method fails.

Run them from the repository root, after the README's install command: ``pwf-dask bench WHAT``
(:mod:`benchmarks.speed`, :mod:`benchmarks.speed_accuracy`, :mod:`benchmarks.stability`) or
``python -m benchmarks.STUDY`` for the studies (``benchmarks/reproduce.sh`` lists them all with
their run times). Results are committed to ``benchmarks/results/``; every table names the
command that made it, the device and the commit. Shared helpers: :mod:`benchmarks.reporting`.
The paper's Algorithm S1 as printed, which the iteration bench times beside the solver, is the
tests' oracle: ``tests/algorithm_s1.py``.
"""
