"""Background of retrieved projections: sample-free pixels and the plane that zeroes them.

Neither PWF filter passes DC (P^-1 and Gamma^2 both vanish there), so the mean phase never
moves from its start; it is fixed afterwards by a plane fitted over sample-free pixels. Those
come from a user mask or are detected: X-ray matter only delays the phase (delta > 0 gives a
negative phase in the exp(+ikz) convention) and only attenuates, so the sample is where the
smoothed phase falls, or the attenuation rises, significantly off the background plane. The
detection never assumes sample-free image borders.

Every function runs on the array module of its input (NumPy, or CuPy with
``cupyx.scipy.ndimage``): on a GPU the detection stays on the device, where it costs
milliseconds against ~1.3 s of host NumPy per 2160 x 2560 projection (docs/gpu.md).
"""

from __future__ import annotations

import numpy as np

from pwf_dask.backend import get_array_module, ndimage, to_numpy

#: the fewest sample-free pixels a background surface is fitted on
MIN_BACKGROUND_PIXELS = 6

#: A retrieved projection's background is flat to a few per cent of the sample's depth, not
#: to its small-scale noise: PWF's low frequencies carry a relative error (the 430 x 2220
#: strip of 172 rad PMMA rods, docs/validation.md: the gaps between the rods sit +-10 rad off
#: one plane under 0.2 rad of noise). Pixels within this fraction of the deepest sample
#: below the plane count as background in a projection (:func:`detect_background`).
PROJECTION_RELATIVE_TOLERANCE = 0.05


def _exponents(degree: int) -> list[tuple[int, int]]:
    """(i, j) of the surface's terms y^i x^j, constant first."""
    return [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]


def _powers(n: int, degree: int, xp=np):
    """(n, degree + 1): the coordinate scaled to [0, 1] (conditioning), to the powers 0..degree."""
    t = xp.arange(n, dtype=xp.float64) / max(n - 1, 1)
    return t[:, None] ** xp.arange(degree + 1)


def fit_surface(image, mask, degree: int = 1):
    """Least-squares polynomial surface of ``degree`` (1: plane, 2: quadratic) through
    ``image[mask]``, evaluated everywhere (:func:`surface_coefficients`, :func:`evaluate_surface`)."""
    xp = get_array_module(image, mask)
    return evaluate_surface(surface_coefficients(image, mask, degree), image.shape, xp)


def surface_coefficients(image, mask, degree: int = 1) -> np.ndarray:
    """The least-squares surface of :func:`fit_surface` as coefficients: a host array ``c`` of
    (degree + 1)^2 with the surface sum_ij c[i, j] y^i x^j, y and x the row and column
    scaled to [0, 1] (terms of total degree above ``degree`` are 0).

    The terms y^i x^j separate, so every sum the normal equations need is a product of small
    matrices, sum_mask y^a x^b z = Y_a^T (mask z) X_b: two passes over the image whatever the
    degree, where a design matrix of every pixel costs one pass per term and a QR of it (91 %
    of a 2560^2 tomogram's time; issue #31). The normal equations square the condition
    number; with coordinates in [0, 1] and degree <= 2 that stays below 1e5, and a
    rank-deficient mask (one row) still gets the minimum-norm least-squares solution. The
    sums are taken on the image's device; the (2 degree + 1)^2 of them are solved on the host.
    """
    xp = get_array_module(image, mask)
    ny, nx = image.shape
    terms = _exponents(degree)
    y_pow, x_pow = _powers(ny, 2 * degree, xp), _powers(nx, 2 * degree, xp)
    moments = to_numpy(y_pow.T @ mask.astype(xp.float64) @ x_pow)  # sum over the mask of y^a x^b
    masked = xp.where(mask, xp.asarray(image, dtype=xp.float64), 0.0)
    projections = to_numpy(y_pow[:, : degree + 1].T @ masked @ x_pow[:, : degree + 1])
    normal = np.array([[moments[i + k, j + m] for k, m in terms] for i, j in terms])
    coef, *_ = np.linalg.lstsq(normal, np.array([projections[i, j] for i, j in terms]), rcond=None)
    c = np.zeros((degree + 1, degree + 1))
    for (i, j), value in zip(terms, coef):
        c[i, j] = value
    return c


def evaluate_surface(coefficients, shape: tuple[int, int], xp=np):
    """The surface of :func:`surface_coefficients` on a frame of ``shape`` (float64)."""
    c = np.asarray(coefficients, dtype=np.float64)
    degree = c.shape[0] - 1
    return _powers(shape[0], degree, xp) @ xp.asarray(c) @ _powers(shape[1], degree, xp).T


def plane_terms(coefficients) -> list[float]:
    """A plane's coefficients (:func:`surface_coefficients`, degree 1) as [constant, row
    slope, column slope] (per frame height and width): what a store keeps per projection."""
    c = np.asarray(coefficients, dtype=np.float64)
    return [float(c[0, 0]), float(c[1, 0]), float(c[0, 1])]


def plane_from_terms(terms, shape: tuple[int, int], xp=np):
    """The plane [constant, row slope, column slope] of :func:`plane_terms` on a frame of ``shape``."""
    a, b, c = (float(t) for t in terms)
    return evaluate_surface(np.array([[a, c], [b, 0.0]]), shape, xp)


def fit_plane(image, mask):
    """Least-squares plane a + b y + c x through ``image[mask]``, evaluated everywhere."""
    return fit_surface(image, mask, 1)


def _robust_sigma(values) -> float:
    xp = get_array_module(values)
    med = xp.median(values)
    return float(1.4826 * xp.median(xp.abs(values - med))) or float(xp.std(values)) or 1.0


def _noise_sigma(image) -> float:
    """Robust small-scale spread: MAD of the image minus its own smoothing (noise and texture)."""
    return _robust_sigma(image - ndimage(get_array_module(image)).gaussian_filter(image, 6.0))


def detect_background(
    phase,
    attenuation=None,
    *,
    smooth_px: float = 3.0,
    k: float = 5.0,
    margin_px: int = 4,
    iterations: int = 20,
    start_quantile: float = 0.9,
    relative_tolerance: float = 0.0,
):
    """Boolean mask of sample-free pixels (True = background).

    Starts from the top decile of the smoothed phase (matter only lowers it), then
    iterates: fit a plane over the current background; call a pixel "sample" where the
    smoothed phase lies more than ``k`` noise sigmas below the plane (or the attenuation
    above it), or more than ``relative_tolerance`` of the deepest sample's depth below it
    where that is larger; grow the sample by ``margin_px`` for edge fringes; refit. The
    noise sigma is measured on small scales, so a sample covering most of the frame cannot
    inflate it. With ``relative_tolerance`` 0 a background that is not flat to ``k`` noise
    sigmas is found in one patch only, and the plane through that patch tilts the frame
    (:data:`PROJECTION_RELATIVE_TOLERANCE`). The mask is of the phase's array module.
    """
    xp = get_array_module(phase)
    nd = ndimage(xp)
    ph = nd.gaussian_filter(xp.asarray(phase, dtype=xp.float64), smooth_px)
    at = None if attenuation is None else nd.gaussian_filter(xp.asarray(attenuation, dtype=xp.float64), smooth_px)
    sig_p = _noise_sigma(ph)
    sig_a = None if at is None else _noise_sigma(at)
    mask = ph >= xp.quantile(ph, start_quantile)
    if at is not None:
        mask &= at <= xp.quantile(at[mask], 0.5)
    for _ in range(iterations):
        sample = _below(ph - fit_plane(ph, mask), k * sig_p, relative_tolerance)
        if at is not None:
            sample |= _below(fit_plane(at, mask) - at, k * sig_a, relative_tolerance)
        if margin_px:
            # CuPy grows by more than one pixel only brute force (the same mask, by definition)
            sample = nd.binary_dilation(sample, iterations=margin_px, brute_force=xp is not np)
        new = ~sample
        if int(new.sum()) < 0.02 * new.size or bool(xp.array_equal(new, mask)):
            break
        mask = new
    return mask


def projection_background(phase, attenuation=None):
    """Sample-free pixels of a retrieved projection (PWF's or a tracking method's):
    :func:`detect_background` with :data:`PROJECTION_RELATIVE_TOLERANCE`."""
    return detect_background(phase, attenuation, relative_tolerance=PROJECTION_RELATIVE_TOLERANCE)


def _below(deviation, noise_tolerance: float, relative_tolerance: float):
    """Where ``deviation`` (image minus its background plane, matter negative) lies below
    the larger of the noise tolerance and ``relative_tolerance`` of its deepest value."""
    tolerance = noise_tolerance
    if relative_tolerance > 0:
        tolerance = max(tolerance, -relative_tolerance * float(deviation.min()))
    return deviation < -tolerance


def zero_background(image, background, degree: int = 1):
    """``image`` minus the surface (plane by default) fitted over ``background`` pixels."""
    _require_background(background)
    xp = get_array_module(image)
    return image - fit_surface(xp.asarray(image, dtype=xp.float64), background, degree)


def _require_background(background) -> None:
    if int(background.sum()) < MIN_BACKGROUND_PIXELS:
        raise ValueError(f"background mask has fewer than {MIN_BACKGROUND_PIXELS} pixels: cannot fit a surface")


def zeroed_with_plane(image, background):
    """(``image`` minus the plane fitted over ``background``, the plane's :func:`plane_terms`):
    :func:`zero_background` that also says what it took away, so that the solver's own psi
    can be rebuilt from a stored projection (a warm start; :func:`plane_from_terms`)."""
    _require_background(background)
    xp = get_array_module(image)
    c = surface_coefficients(xp.asarray(image, dtype=xp.float64), background, 1)
    return image - evaluate_surface(c, image.shape, xp), plane_terms(c)
