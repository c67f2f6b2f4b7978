"""Preconditioned Wirtinger flow, Algorithms S1 and S2: the solver (solver) and its fused element-wise passes (kernels).

Pure functions on NumPy or CuPy arrays; nothing here touches Dask or a store.
"""
