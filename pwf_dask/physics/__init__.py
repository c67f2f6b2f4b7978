"""Physics of the set-up: its geometry (geometry), free-space optics and the paper's Fourier filters
(optics), refractive indices (materials), sandpaper diffusers (diffusers), detector defects
(detector), the background plane (background) and the single-material prior, Paganin's filter
(single_material).

Pure functions on NumPy or CuPy arrays; nothing here touches Dask or a store.
"""
