"""Tomography: filtered back projection and the rotation centre (tomography), gridding FBP (gridrec),
Fourier shell correlation (fsc). Per slice, on NumPy or CuPy arrays.
"""
