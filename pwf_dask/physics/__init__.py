"""Physics of the set-up: its geometry (geometry), free-space optics and the paper's Fourier filters
(optics), refractive indices (materials), sandpaper diffusers (diffusers), detector defects
(detector) and the background plane (background).

Pure functions on NumPy or CuPy arrays; nothing here touches Dask or a store.
"""
