"""Sandpaper diffusers: grit sizes, grain shapes, and the coherent speckle they make.

The paper's diffuser is four layers of P3000 sandpaper (Methods, Experimental setup). A layer is
abrasive grains (silicon carbide) on a backing; what the X-rays see is the grains' projected
thickness T_r, a phase screen t_r = exp[-k (i delta + beta) T_r]. This module is the one place
that knows what such a screen looks like; :mod:`pwf_dask.simulation` draws scenes with it and
:mod:`pwf_dask.calibration` fits the coherence lengths against the speckle it makes.

* :data:`FEPA_P_GRIT_DIAMETER_M` - median grain diameters of the coated-abrasive P grades;
* :func:`grain_thickness` - T_r of several layers of grains with log-normal sizes, of one of
  :data:`GRAIN_SHAPES`: ``"spheres"`` (smooth grains, a square-root rim), ``"faceted"``
  (pyramids on 3- to 6-sided bases, the angular crystals of crushed SiC: a linear rim and
  ridges) or ``"mixed"`` (half of each);
* :func:`coherent_speckle` - the detector intensity |P_L{t}|^2 such a screen makes with a
  fully coherent beam, pixel-integrated, without noise.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from pwf_dask.backend import FFT
from pwf_dask.physics import optics
from pwf_dask.physics.materials import delta_beta

#: Median grain diameter (d_s50) of FEPA P grades for coated abrasives, FEPA 43-2 / ISO 6344-3
#: micro grits (P240-P2500). P3000 is finer than the standard's range: 6.5 um is the
#: manufacturers' figure (the paper's Starcke 991A P3000).
FEPA_P_GRIT_DIAMETER_M: dict[str, float] = {
    "P240": 58.5e-6,
    "P280": 52.2e-6,
    "P320": 46.2e-6,
    "P360": 40.5e-6,
    "P400": 35.0e-6,
    "P500": 30.2e-6,
    "P600": 25.8e-6,
    "P800": 21.8e-6,
    "P1000": 18.3e-6,
    "P1200": 15.3e-6,
    "P1500": 12.6e-6,
    "P2000": 10.3e-6,
    "P2500": 8.4e-6,
    "P3000": 6.5e-6,
}

#: The paper's diffuser (Methods): four layers of P3000 silicon-carbide sandpaper.
DEFAULT_GRIT = "P3000"
DEFAULT_LAYERS = 4
DEFAULT_MATERIAL = "silicon carbide"
#: Log-normal spread (sigma of ln d) of the grain sizes: FEPA's micro-grit tolerances keep the
#: bulk of a grade within about a factor of two of its median (3 % coarser than ~2 d50, 94 %
#: coarser than ~0.55 d50), i.e. sigma ~ 0.4.
FEPA_SPREAD = 0.4
#: Fraction of each layer's area the grains cover.
DEFAULT_COVERAGE = 0.6

GRAIN_SHAPES = ("spheres", "faceted", "mixed")


def grit_radius_m(grit: str) -> float:
    """Median grain radius of a FEPA P grade (``"P3000"``); one-line error for an unknown one."""
    key = str(grit).upper()
    if key not in FEPA_P_GRIT_DIAMETER_M:
        raise ValueError(f"unknown grit {grit!r}: choose one of {', '.join(FEPA_P_GRIT_DIAMETER_M)}")
    return 0.5 * FEPA_P_GRIT_DIAMETER_M[key]


def _sphere_chord(yy, xx, rp):
    return 2.0 * np.sqrt(np.clip(rp * rp - yy * yy - xx * xx, 0, None))


def _pyramid(yy, xx, rp, sides: int, turn: float):
    """A pyramid of height 2 rp over a regular polygon of apothem rp: thickness falls linearly
    from the apex to every facet's base edge."""
    # the facets' maximum and the slope in place: two arrays, not a stack of facets, and no
    # fresh (page-faulting) array per pass on the large grains' kernels
    reach = facet = None
    for j in range(sides):
        angle = turn + 2 * np.pi * j / sides
        facet = np.add(xx * np.cos(angle), yy * np.sin(angle), out=facet)
        reach = facet.copy() if reach is None else np.maximum(reach, facet, out=reach)
    np.divide(reach, rp, out=reach)
    np.subtract(1.0, reach, out=reach)
    np.clip(reach, 0, None, out=reach)
    return np.multiply(2.0 * rp, reach, out=reach)


def _grain_kernels(rp: float, grain_shape: str, rng: np.random.Generator):
    """Thickness kernels (grid cells) of one grain size, averaged over 4 x 4 sub-samples of each
    cell, and the share of the grains each kernel stands for. The kernel box reaches rp + 1
    cells from the centre, so a triangle's tips (2 rp out) are cut: up to ~10 % of its volume
    on large grains (``tests/test_calibration.py`` measures the volumes)."""
    half = int(np.ceil(rp)) + 1
    yy, xx = np.mgrid[-half : half + 1, -half : half + 1].astype(float)
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    profiles = []
    if grain_shape in ("spheres", "mixed"):
        profiles.append(lambda y, x: _sphere_chord(y, x, rp))
    if grain_shape in ("faceted", "mixed"):
        # a few orientations and polygons stand for the many: each kernel takes an equal share
        for sides in (3, 4, 5, 6):
            turn = rng.uniform(0, 2 * np.pi)
            profiles.append(lambda y, x, s=sides, a=turn: _pyramid(y, x, rp, s, a))
    kernels = []
    # the 16 sub-samples of every cell at once (one array pass per profile, not 16), as
    # (4, 1, n, 1) rows and (1, 4, 1, n) columns: each profile's x and y terms are formed on
    # those and meet in one broadcast pass (the large grains' faceted kernels cost the template
    # calibration half its time when both were full (16, n, n) grids)
    cells = yy[:, 0]
    y = (cells[None, :] + sub[:, None])[:, None, :, None]
    x = (cells[None, :] + sub[:, None])[None, :, None, :]
    for profile in profiles:
        k = profile(y, x).reshape(16, *yy.shape).sum(axis=0) / 16.0
        kernels.append((yy.astype(int), xx.astype(int), k))
    if grain_shape == "mixed":  # half the grains round, half faceted
        shares = [0.5] + [0.5 / (len(kernels) - 1)] * (len(kernels) - 1)
    else:
        shares = [1.0 / len(kernels)] * len(kernels)
    return kernels, shares


def grain_thickness(
    shape: tuple[int, int],
    spacing_m: float,
    rng: np.random.Generator,
    *,
    radius_median_m: float,
    radius_spread: float = FEPA_SPREAD,
    layers: float = DEFAULT_LAYERS,
    coverage: float = DEFAULT_COVERAGE,
    grain_shape: str = "spheres",
    radius_bins: int = 8,
) -> np.ndarray:
    """Projected thickness T_r (m) of ``layers`` layers of abrasive grains on a periodic grid.

    Grain radii are log-normal (median ``radius_median_m``, sigma ``radius_spread``), binned
    into ``radius_bins`` sizes over +-2 sigma; grain centres are uniform; each layer covers
    ``coverage`` of the area. Grain edges are sharp at any grid scale (4 x 4 sub-samples).
    """
    if grain_shape not in GRAIN_SHAPES:
        raise ValueError(f"unknown grain shape {grain_shape!r}: choose one of {', '.join(GRAIN_SHAPES)}")
    if not (radius_median_m > 0 and radius_spread >= 0 and layers > 0 and coverage > 0):
        raise ValueError(
            "grain_thickness needs radius_median_m > 0, radius_spread >= 0, layers > 0 and coverage > 0; got "
            f"{radius_median_m}, {radius_spread}, {layers}, {coverage}"
        )
    from scipy.special import ndtr  # the normal CDF; scipy.stats would cost 0.4 s to import

    ny, nx = shape
    log_median = np.log(radius_median_m)
    edges = np.exp(np.linspace(log_median - 2 * radius_spread, log_median + 2 * radius_spread, radius_bins + 1))
    centres = np.sqrt(edges[:-1] * edges[1:])
    if radius_spread > 0:
        frac = np.diff(ndtr((np.log(edges) - log_median) / radius_spread))
    else:
        frac = np.full(radius_bins, 1.0)
    frac /= frac.sum()
    mean_area = float(np.sum(frac * np.pi * centres**2))
    n_total = layers * coverage * ny * nx * spacing_m**2 / mean_area
    thickness = np.zeros(ny * nx)
    for r, f in zip(centres, frac):
        kernels, shares = _grain_kernels(r / spacing_m, grain_shape, rng)
        for (ky, kx, k), share in zip(kernels, shares):
            n = rng.poisson(n_total * f * share)
            if n == 0:
                continue
            _splat(thickness, (ny, nx), rng.integers(0, ny, n), rng.integers(0, nx, n), ky, kx, k * spacing_m)
    return thickness.reshape(shape)


#: grain-by-kernel index pairs per batch of :func:`_splat` (bounds its temporaries, ~50 MB)
_SPLAT_BATCH = 1 << 22


def _splat(thickness, shape, cy, cx, ky, kx, kernel) -> None:
    """Add ``kernel`` (cell offsets ky, kx) centred on every grain (cy, cx), periodically.

    The same sum as convolving the grains' impulses with the kernel by FFT, which the grains'
    sparsity makes wasteful: a few thousand grains of ~150 kernel cells against two full-frame
    FFTs per grain size and shape (8 x 5 of them); the template calibration, which synthesises
    26 such diffusers then, became ~5x faster. A compiled loop (numba) adds each cell in place, ~9x
    faster again than the index arrays and ``bincount`` it falls back to without numba; the two
    differ only in the order of the float64 additions."""
    ny, nx = shape
    ky, kx, w = ky.ravel(), kx.ravel(), kernel.ravel()
    keep = w != 0
    ky, kx, w = ky[keep], kx[keep], w[keep]
    loop = _splat_loop()
    if loop is not None:
        loop(
            thickness,
            ny,
            nx,
            np.asarray(cy, np.int64),
            np.asarray(cx, np.int64),
            ky.astype(np.int64),
            kx.astype(np.int64),
            w,
        )
        return
    step = max(1, _SPLAT_BATCH // max(1, w.size))
    for i in range(0, cy.size, step):
        rows = (cy[i : i + step, None] + ky) % ny
        cols = (cx[i : i + step, None] + kx) % nx
        flat = (rows * nx + cols).ravel()
        thickness += np.bincount(flat, weights=np.broadcast_to(w, (rows.shape[0], w.size)).ravel(), minlength=ny * nx)


def _splat_cells(thickness, ny, nx, cy, cx, ky, kx, w):
    for i in range(cy.size):
        for j in range(w.size):
            # a wrap is rare (cells off the grid's edge): a test, not an integer division per cell
            row, col = cy[i] + ky[j], cx[i] + kx[j]
            if row < 0 or row >= ny:
                row %= ny
            if col < 0 or col >= nx:
                col %= nx
            thickness[row * nx + col] += w[j]


@lru_cache(maxsize=1)
def _splat_loop():
    """:func:`_splat_cells` compiled (and cached on disk) by numba, or None without numba."""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; a bare checkout may lack it
        return None
    return numba.njit(_splat_cells, nogil=True, cache=True)


def _screen_cells(thickness, rate):
    out = np.empty(thickness.size, np.complex128)
    flat = thickness.ravel()
    for i in range(flat.size):
        out[i] = np.exp(rate * flat[i])
    return out.reshape(thickness.shape)


def _binned_intensity_cells(field, s):
    ny, nx = field.shape[0] // s, field.shape[1] // s
    out = np.zeros((ny, nx))
    for i in range(ny * s):
        for j in range(nx * s):
            z = field[i, j]
            out[i // s, j // s] += z.real * z.real + z.imag * z.imag
    return out / (s * s)


@lru_cache(maxsize=1)
def _template_loops():
    """:func:`_screen_cells` and :func:`_binned_intensity_cells` compiled by numba (one pass
    each, the GIL released so that the calibration's templates simulate side by side), or None
    without numba. The screen is NumPy's complex exp to the bit; the binned intensity differs
    from NumPy's ``mean`` only in the order of four float64 additions."""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; a bare checkout may lack it
        return None
    return (
        numba.njit(_screen_cells, nogil=True, cache=True),
        numba.njit(_binned_intensity_cells, nogil=True, cache=True),
    )


def transmission(thickness_m: np.ndarray, energy_eV: float, material: str = DEFAULT_MATERIAL) -> np.ndarray:
    """t_r = exp[-k (i delta + beta) T_r] of a thin screen of ``material`` (the exp(+ikz) convention)."""
    d, b = delta_beta(material, energy_eV)
    k = 2 * np.pi / optics.wavelength_m(energy_eV)
    return np.exp((-1j * d - b) * k * thickness_m)


@lru_cache(maxsize=4)
def _free_space_kernel(shape: tuple[int, int], spacing_m: float, wavelength: float, distance_m: float) -> np.ndarray:
    """:func:`pwf_dask.physics.optics.angular_spectrum_kernel` of :func:`coherent_speckle`'s grid,
    kept for the next call: the calibration's templates simulate up to 26 diffusers, nearly all on
    one grid, and the kernel cost as much as the grains' splatting."""
    kernel = optics.angular_spectrum_kernel(shape, spacing_m, wavelength, distance_m, np, np.complex128)
    kernel.flags.writeable = False
    return kernel


def coherent_speckle(
    frame_shape: tuple[int, int],
    *,
    pixel_size_m: float,
    energy_eV: float,
    distance_m: float,
    radius_median_m: float,
    grain_shape: str = "mixed",
    material: str = DEFAULT_MATERIAL,
    layers: float = DEFAULT_LAYERS,
    radius_spread: float = FEPA_SPREAD,
    seed: int = 0,
    oversample: int = 2,
    fft_workers: int | None = None,
) -> np.ndarray:
    """|P_L{t}|^2 of a fresh diffuser ``distance_m`` before the detector, fully coherent beam,
    integrated over ``pixel_size_m`` pixels (the grains on a grid ``oversample`` times finer),
    mean 1, without noise: the speckle whose spectrum the coherence blur multiplies.
    ``fft_workers``: the propagation's FFT threads (default: this process's budget)."""
    s = int(oversample)
    ny, nx = frame_shape
    fine = (ny * s, nx * s)
    spacing = pixel_size_m / s
    rng = np.random.default_rng(seed)
    thickness = grain_thickness(
        fine,
        spacing,
        rng,
        radius_median_m=radius_median_m,
        radius_spread=radius_spread,
        layers=layers,
        grain_shape=grain_shape,
    )
    loops = _template_loops()
    if loops is None:
        t = transmission(thickness, energy_eV, material)
    else:
        d, b = delta_beta(material, energy_eV)
        t = loops[0](thickness, complex(-b, -d) * (2 * np.pi / optics.wavelength_m(energy_eV)))
    if distance_m == 0:
        v = t
    else:
        fft = FFT.for_module(np, fft_workers)
        spectrum = fft.fft2(t, overwrite=True)
        spectrum *= _free_space_kernel(fine, spacing, optics.wavelength_m(energy_eV), distance_m)
        v = fft.ifft2(spectrum, overwrite=True)
    if loops is None:
        intensity = (v.real**2 + v.imag**2).reshape(ny, s, nx, s).mean(axis=(1, 3))
    else:
        intensity = loops[1](v, s)
    return intensity / intensity.mean()
