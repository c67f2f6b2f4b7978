"""Coherence calibration from the reference speckle (Methods: IOTF, Eq. (IOTF) and Eq. (sigert)).

* :func:`fit_coherence_lengths` (and its pair-returning :func:`coherence_lengths`) - x_coh,
  y_coh of the IOTF, Eq. (IOTF). By default the reference's spectrum is fitted as simulated
  coherent sandpaper speckle at the scan's geometry (:mod:`pwf_dask.physics.diffusers`) times the
  Gaussian IOTF, the template of least chi^2 winning (``method="template"``); the paper's
  Siegert fit, Eq. (sigert), the Gaussian alone, is ``method="gaussian"``
  (docs/methods.md, "Coherence calibration").
* :func:`photon_noise_pct` - the sample image's photon noise from its white spectral floor
  (the level of ``alpha="discrepancy"``); :func:`relative_noise_variance` - a frame's, over
  its own mean (the diffuser's Wiener NSR at the sample's noise).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import ndimage

from pwf_dask.backend import default_fft_workers, get_array_module, to_numpy
from pwf_dask.physics.diffusers import DEFAULT_MATERIAL


def _axis_power_spectra(img: np.ndarray):
    """1-D power spectra along x and along y (Hann-windowed, averaged over the other axis),
    their frequencies (cycles/pixel), and the white-noise floor from the 2-D spectrum's
    corners beyond the Nyquist circle, where the IOTF has removed all speckle."""
    ny, nx = img.shape
    win = np.outer(np.hanning(ny), np.hanning(nx))
    spec = np.abs(np.fft.fft2((img - img.mean()) * win)) ** 2
    v, u = np.fft.fftfreq(ny)[:, None], np.fft.fftfreq(nx)[None, :]
    corners = (u * u + v * v) > 0.3
    # a white-noise periodogram is exponentially distributed: its median is ln 2 of the
    # mean floor that the 1-D spectra carry (the median alone left 31 % of it on the flank)
    noise = float(np.median(spec[np.broadcast_to(corners, spec.shape)])) / np.log(2.0)
    px = spec.mean(axis=0)[: nx // 2]
    py = spec.mean(axis=1)[: ny // 2]
    return (np.fft.fftfreq(nx)[: nx // 2], px), (np.fft.fftfreq(ny)[: ny // 2], py), noise


def _fit_gaussian_flank(freq: np.ndarray, power: np.ndarray, noise: float) -> float:
    """Width c of exp(-pi c^2 q^2) fitted to the decaying flank of ``power - noise``.

    The flank runs from where the spectrum has fallen to 70 % of its peak down to 0.3 %
    of it (or the noise): there the IOTF^2 dominates the shape.
    """
    sig = power - noise
    smooth = np.convolve(sig, np.ones(3) / 3, mode="same")
    ipk = int(np.argmax(smooth[1:])) + 1
    peak = smooth[ipk]
    sel = np.zeros(freq.shape, bool)
    for i in range(ipk, freq.size):
        if smooth[i] < max(3e-3 * peak, 3 * noise / np.sqrt(max(power.size, 1))):
            break
        # a point the noise pushed to or below zero has no logarithm to fit
        if smooth[i] <= 0.7 * peak and sig[i] > 0:
            sel[i] = True
    if sel.sum() < 3:
        raise ValueError("too few frequencies on the spectrum's flank")
    q2 = freq[sel] ** 2
    slope, _ = np.polyfit(q2, np.log(sig[sel]), 1, w=np.sqrt(sig[sel] / peak))
    if not slope < 0:
        raise ValueError("the spectrum does not decay")
    return float(np.sqrt(-slope / np.pi))


def _gaussian_flank_lengths(img: np.ndarray, pixel_size_m: float) -> tuple[float, float]:
    """The Gaussian model alone, Eq. (sigert): exp(-pi c^2 q^2) fitted on the decaying flank of
    the 1-D power spectra along x and y (each averaged over the other axis), white noise
    subtracted. The paper fits the same Gaussian to the autocorrelation; in Fourier space the
    band-pass coherent speckle of a phase diffuser (little power at low frequencies, negative
    lobes in the autocorrelation) does not bias it short. Lengths include the pixel's blur.
    Exact for delta-correlated speckle; long when the coherent speckle's own spectrum falls
    across the flank (sandpaper grains: :func:`fit_coherence_lengths`)."""
    img = img - ndimage.gaussian_filter(img, 32.0, mode="reflect")
    (fx, px), (fy, py), noise = _axis_power_spectra(img)
    out = []
    for name, f, p in (("x", fx, px), ("y", fy, py)):
        try:
            c = _fit_gaussian_flank(f, p, noise)
        except ValueError as exc:
            raise ValueError(
                f"coherence-length fit along {name} failed ({exc}): the reference shows no resolvable "
                "speckle blur; give coherence_length_x_m and coherence_length_y_m explicitly"
            ) from None
        out.append(c * pixel_size_m)
    return out[0], out[1]


# --- coherence lengths: the IOTF fitted jointly with the diffuser's own speckle spectrum -----

#: largest Welch tile (px) of the reference's power spectrum (:func:`spectrum_tile`)
SPECTRUM_TILE_PX = 128
#: lowest frequency (cycles/px) of the fit: below it lie the flat field's residue and the
#: grains' size peak, which the data measure so precisely that a template's realisation noise
#: there outweighs the flank that carries the coherence blur
FIT_MIN_FREQUENCY = 0.06
#: only frequencies where the spectrum stands this many times above the white noise floor
FIT_MIN_SIGNAL_TO_NOISE = 3.0
#: the fewest such frequencies a fit of (log A, x^2, y^2) is made on
FIT_MIN_POINTS = 12
#: below this many photons a pixel (1 / the white floor of the mean-normalised reference) the
#: frequencies are chosen on the spectrum averaged over +-:data:`LOW_DOSE_SELECTION_HALF_WIDTH`:
#: there every fitted frequency lies near the noise cut, and choosing on each bin's own noisy
#: value keeps those that noise lifted, which read the flank high and the lengths short
#: (100 ph/px: -5.1 % mean over 36 developed-speckle references, -1.7 % so chosen; the
#: issue's 1e3-1e5 ph/px, all above it, fit exactly as before; docs/methods.md)
LOW_DOSE_PHOTONS = 500.0
#: cycles per pixel: +-2 bins of a 128 px tile (5 x 5), +-1 of a 64 px one, none of 32 px: a
#: fixed width in frequency, as a wider one would carry the strong low frequencies' power up
#: the flank
LOW_DOSE_SELECTION_HALF_WIDTH = 2.0 / 128.0
#: median grain radii of the templates: 0.5-16 um in steps of 2^(1/2), each fitted; below
#: :data:`TEMPLATE_REFINE_BELOW_PX` the best one's neighbours at 2^(+-1/4) are fitted too
TEMPLATE_RADII_M = tuple(0.5e-6 * 2 ** (k / 2) for k in range(11))
#: grain radius (detector pixels) below which the best template's 2^(+-1/4) neighbours are
#: fitted too. Templates of grains under ~3 px differ in shape over the fitted band (log
#: residual 0.13-0.76 against the 6 px template at 0.65 um pixels, against 0.05-0.09 among
#: coarser ones), so the finer step pays there: at 6.5 um pixels (grains of 0.3-2 px; the
#: sweep's "real-data regime") it took 5.15 um grains from +7.0 / +9.8 % to +3.8 / +5.3 %.
#: Above, it only adds candidates on a flat chi^2: on developed speckle at 300 ph/px a 2.4 um
#: neighbour beat the white template and read 21 % short (``tests/test_calibration.py``).
#: docs/methods.md, "Coherence calibration"
TEMPLATE_REFINE_BELOW_PX = 3.0
#: largest template grain radius in detector pixels. A coarser grain's first spectral zero
#: (0.61 / r cycles/px) lies below :data:`FIT_MIN_FREQUENCY`: over the fitted band its
#: spectrum is the edges' tail, of one shape from ~6 px on (log-residual 0.05-0.09 at 0.65 um
#: pixels) but for a Gaussian factor that trades against the IOTF's width, so the data cannot
#: choose among such templates (a flat chi^2). Picked on 20 of the 80 references (the worst
#: errors among them: faceted 3.2 um grains +7.4 %, 2 / 2.5 um coherence +23.9 %), they cost
#: 40 % of the fit (frames of 16 radii). docs/methods.md, "Coherence calibration".
TEMPLATE_MAX_RADIUS_PX = 12.0
TEMPLATE_SEEDS = (1, 2)
#: methods of :func:`fit_coherence_lengths`
COHERENCE_METHODS = ("template", "gaussian")
#: the calibration every caller defaults to: the IOTF fitted with the diffuser's own spectrum
DEFAULT_COHERENCE_METHOD = "template"


def _tiles(shape: tuple[int, int], tile: tuple[int, int]):
    (ny, nx), (ty, tx) = shape, tile
    for y0 in range(0, ny - ty + 1, max(ty // 2, 1)):
        for x0 in range(0, nx - tx + 1, max(tx // 2, 1)):
            yield slice(y0, y0 + ty), slice(x0, x0 + tx)


def _symmetrised(a: np.ndarray) -> np.ndarray:
    """The mean of a(u, v), a(-u, v), a(u, -v), a(-u, -v) on fft grids: equal in expectation
    for a spectrum taken through a symmetric window (a Gaussian IOTF, an isotropic diffuser)."""

    def flip(b, axis):
        return np.roll(np.flip(b, axis), 1, axis)

    return 0.25 * (a + flip(a, 0) + flip(a, 1) + flip(flip(a, 0), 1))


def speckle_spectrum(img: np.ndarray, tile: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Welch estimate of the 2-D power spectrum of ``img`` (Hann tiles of ``tile`` px, half
    overlapping, each tile's mean removed; units: variance per frequency bin) and the variance
    of that estimate from the tiles' own scatter, both symmetrised (:func:`_symmetrised`).

    The scatter is measured, not taken from Gaussian statistics: the speckle of coarse grains
    is far from Gaussian (bright caustics), and its periodogram scatters 2-4x more.
    """
    win = np.outer(np.hanning(tile[0]), np.hanning(tile[1]))
    norm = float(np.sum(win**2))
    s1 = np.zeros(tile)
    s2 = np.zeros(tile)
    n = 0
    for rows, cols in _tiles(img.shape, tile):
        a = img[rows, cols]
        p = np.abs(np.fft.fft2((a - a.mean()) * win)) ** 2 / norm
        s1 += p
        s2 += p * p
        n += 1
    mean = s1 / n
    var = np.maximum(s2 / n - mean**2, 0.0) / max(n - 1, 1)
    # a(u, v) and a(-u, -v) are one number: symmetrising halves the variance, not quarters it
    return _symmetrised(mean), _symmetrised(var) / 2.0


def spectrum_tile(frame_shape: tuple[int, int]) -> tuple[int, int]:
    """Welch tile per axis: the largest power of two up to half the frame (so that at least
    three half-overlapping tiles measure the scatter), at most :data:`SPECTRUM_TILE_PX`, at
    least 32 px (or the frame)."""

    def side(n: int) -> int:
        power = 1 << max(int(np.log2(max(n // 2, 1))), 0)
        return min(n, max(32, min(SPECTRUM_TILE_PX, power)))

    return side(frame_shape[0]), side(frame_shape[1])


def white_noise_floor(img: np.ndarray) -> float:
    """Photon noise per frequency bin (the units of :func:`speckle_spectrum`): the median of the
    periodogram beyond the Nyquist circle, where the IOTF has removed all speckle, over ln 2 (a
    white-noise periodogram is exponential: its median alone left 31 % of the floor)."""
    xp = get_array_module(img)  # NumPy or CuPy: a device frame is read where it lies
    ny, nx = img.shape
    spec = xp.abs(xp.fft.fft2(img - img.mean())) ** 2 / (ny * nx)
    v, u = np.fft.fftfreq(ny)[:, None], np.fft.fftfreq(nx)[None, :]
    corners = xp.asarray(np.broadcast_to((u * u + v * v) > 0.3, spec.shape))
    return float(xp.median(spec[corners])) / np.log(2.0)


def photon_noise_pct(image, mean_reference: float) -> float:
    """RMS photon noise of ``image`` in % of the mean reference, from its white spectral floor
    (:func:`white_noise_floor`; the IOTF has blurred away every structure out there). This is
    the level :func:`pwf_dask.pwf.solver.discrepancy_alpha` fits the data down to."""
    return 100.0 * float(np.sqrt(white_noise_floor(np.asarray(image, np.float64) / mean_reference)))


def _pixel_transfer_squared(tile: tuple[int, int]) -> np.ndarray:
    """|sinc(u) sinc(v)|^2 on a tile's fft grid (cycles per pixel): what a detector pixel
    does to the spectrum of the intensity it integrates."""
    v, u = np.fft.fftfreq(tile[0])[:, None], np.fft.fftfreq(tile[1])[None, :]
    return (np.sinc(u) * np.sinc(v)) ** 2


def _ring_average(spectrum: np.ndarray) -> np.ndarray:
    """``spectrum`` averaged over rings of |q| (cycles per pixel, width one bin of the larger
    tile side) and put back on its grid by linear interpolation; the pixel's transfer, which
    is not isotropic, is divided out first and multiplied back after."""
    tile = spectrum.shape
    mtf2 = _pixel_transfer_squared(tile)
    v, u = np.fft.fftfreq(tile[0])[:, None], np.fft.fftfreq(tile[1])[None, :]
    q = np.broadcast_to(np.hypot(u, v), tile).ravel()
    width = 1.0 / max(tile)
    ring = np.floor(q / width).astype(int)
    total = np.bincount(ring, (spectrum / mtf2).ravel())
    count = np.bincount(ring)
    filled = count > 0
    centres = (np.flatnonzero(filled) + 0.5) * width
    profile = total[filled] / count[filled]
    return np.interp(q, centres, profile).reshape(tile) * mtf2


@lru_cache(maxsize=256)
def _template_spectrum(
    tile: tuple[int, int],
    pixel_size_m: float,
    energy_eV: float,
    distance_m: float,
    material: str,
    radius_m: float,
) -> np.ndarray:
    """Spectrum of the coherent speckle of mixed grains of median radius ``radius_m``
    (:func:`pwf_dask.physics.diffusers.coherent_speckle`), taken exactly as the data's
    (:func:`speckle_spectrum`, the same tiles and window), averaged over
    :data:`TEMPLATE_SEEDS` and over rings of |q| (the grains are isotropic): noise-free next to
    the data's, so every template is judged with the data's own error bars."""
    from pwf_dask.physics import diffusers

    side = max(256, int(16 * radius_m / pixel_size_m))
    frame = (max(side, 2 * tile[0]), max(side, 2 * tile[1]))
    total = np.zeros(tile)
    for seed in TEMPLATE_SEEDS:
        speckle = diffusers.coherent_speckle(
            frame,
            pixel_size_m=pixel_size_m,
            energy_eV=energy_eV,
            distance_m=distance_m,
            radius_median_m=radius_m,
            grain_shape="mixed",
            material=material,
            seed=seed,
            fft_workers=1,  # the templates are simulated side by side (_template_spectra)
        )
        total += speckle_spectrum(speckle, tile)[0]
    return _ring_average(total / len(TEMPLATE_SEEDS))


def _template_spectra(geometry: tuple, radii) -> list[np.ndarray]:
    """:func:`_template_spectrum` of each grain radius at ``geometry`` (its other arguments),
    the templates not yet kept simulated side by side on this process's cores: each is
    independent and deterministic (fixed seeds), and numba's splat, NumPy's large-array passes
    and the FFTs release the GIL, so threads give the same templates sooner."""
    threads = min(len(radii), default_fft_workers())
    if threads <= 1:
        return [_template_spectrum(*geometry, radius) for radius in radii]
    with ThreadPoolExecutor(threads, thread_name_prefix="pwf-template") as pool:
        # the largest grains' templates (the largest frames) first, so that none is left alone
        # at the end
        started = {radius: pool.submit(_template_spectrum, *geometry, radius) for radius in sorted(radii)[::-1]}
        return [started[radius].result() for radius in radii]


def template_radii_m(pixel_size_m: float) -> tuple[float, ...]:
    """The grain radii of :data:`TEMPLATE_RADII_M` up to :data:`TEMPLATE_MAX_RADIUS_PX` pixels
    (the smallest one on any pixel)."""
    kept = tuple(r for r in TEMPLATE_RADII_M if r <= TEMPLATE_MAX_RADIUS_PX * pixel_size_m)
    return kept or TEMPLATE_RADII_M[:1]


def fit_selection_spectrum(spectrum: np.ndarray, noise: float) -> np.ndarray:
    """The spectrum whose bins above the noise cut :func:`_fit_iotf` fits: ``spectrum`` itself,
    or below :data:`LOW_DOSE_PHOTONS` photons a pixel its mean over
    +-:data:`LOW_DOSE_SELECTION_HALF_WIDTH` cycles per pixel (the fft grid wraps), so that
    which frequencies are fitted no longer depends on their own noise."""
    if not noise * LOW_DOSE_PHOTONS > 1.0:
        return spectrum
    size = [2 * int(LOW_DOSE_SELECTION_HALF_WIDTH * n + 1e-9) + 1 for n in spectrum.shape]
    return ndimage.uniform_filter(spectrum, size, mode="wrap")


def _above_noise(spectrum: np.ndarray, selection: np.ndarray, noise: float) -> np.ndarray:
    """The bins the IOTF fit may use: ``selection`` 3x above the white floor, and the bin's own
    value above it (log(S - N) defined; implied when ``selection`` is ``spectrum``)."""
    return (selection > FIT_MIN_SIGNAL_TO_NOISE * noise) & (spectrum > noise)


def _fit_iotf(spectrum, variance, noise: float, template, selection):
    """Weighted least squares of log(S - N) = log A + log T - pi (u^2 x^2 + v^2 y^2): the
    template T times Eq. (IOTF) squared, linear in (log A, x^2, y^2) with u, v in cycles per
    pixel and lengths in pixels, weighted by the data's own scatter (the templates are
    noise-free: :func:`_template_spectrum`), over the frequencies where ``selection``
    (:func:`fit_selection_spectrum`) stands 3x above the noise.
    Returns (x_px, y_px, chi2, points), or None without positive lengths or with too few
    frequencies above the noise."""
    ty, tx = spectrum.shape
    v = np.broadcast_to(np.fft.fftfreq(ty)[:, None], spectrum.shape)
    u = np.broadcast_to(np.fft.fftfreq(tx)[None, :], spectrum.shape)
    q = np.hypot(u, v)
    use = (
        _above_noise(spectrum, selection, noise)
        & (q >= FIT_MIN_FREQUENCY)
        & (q < 0.5)
        & (template > 0)
        & (u >= 0)
        & (v >= 0)
    )
    if use.sum() < FIT_MIN_POINTS:
        return None
    signal = spectrum[use] - noise
    y = np.log(signal) - np.log(template[use])
    sd = np.maximum(np.sqrt(variance[use]) / signal, 1e-3)  # a scatter-free bin must not weigh infinitely
    design = np.stack([np.ones(y.size), -np.pi * u[use] ** 2, -np.pi * v[use] ** 2], axis=1)
    coef, *_ = np.linalg.lstsq(design / sd[:, None], y / sd, rcond=None)
    if not (coef[1] > 0 and coef[2] > 0):
        return None
    chi2 = float(np.sum(((design @ coef - y) / sd) ** 2))
    return float(np.sqrt(coef[1])), float(np.sqrt(coef[2])), chi2, int(use.sum())


@dataclass(frozen=True)
class CoherenceFit:
    """Coherence lengths fitted to a reference, and what the fit chose (:func:`fit_coherence_lengths`)."""

    x_m: float
    y_m: float
    method: str  # "template" or "gaussian"
    #: the coherent speckle the IOTF was fitted against: "mixed grains" (of median radius
    #: ``grain_radius_m``) or "white" (delta-correlated, the Siegert premise); "" for "gaussian"
    template: str = ""
    grain_radius_m: float | None = None
    #: the winning template's chi^2 per frequency fitted (:func:`_fit_iotf`)
    chi2_per_point: float | None = None
    points: int = 0
    #: the reference's dose as the fit read it: 1 / the white floor of the mean-normalised
    #: reference (photons a pixel, flat and dark noise included); below
    #: :data:`LOW_DOSE_PHOTONS` the frequencies were chosen on the smoothed spectrum ("template")
    reference_photons_per_px: float | None = None

    @property
    def includes_pixel_blur(self) -> bool:
        """The Gaussian fit's lengths carry the pixel's blur; the template fit's do not."""
        return self.method == "gaussian"


def fit_coherence_lengths(
    reference,
    pixel_size_m: float,
    *,
    energy_eV: float | None = None,
    diffuser_detector_distance_m: float | None = None,
    diffuser_material: str = DEFAULT_MATERIAL,
    method: str = DEFAULT_COHERENCE_METHOD,
) -> CoherenceFit:
    """Coherence lengths (x_coh, y_coh) from the reference speckle (Methods, IOTF).

    The reference's power spectrum is the coherent speckle's own spectrum C(q), times IOTF(q)^2
    of Eq. (IOTF), times the pixel's transfer function squared, plus white photon noise. The
    paper fits the Gaussian alone (the Siegert relation, Eq. (sigert)), which presumes C flat:
    speckle grains far finer than the coherence length. Sandpaper's are not (P3000: 6.5 um
    across, against 3.5-4.3 um), so C falls across the IOTF's flank too and the Gaussian alone
    came out 11-52 % long over grains of 1-5 um radius, L2 of 10-100 mm and two grain shapes
    (docs/methods.md, "Coherence calibration").

    ``method="template"`` (default) fits the IOTF jointly with C. C is the simulated coherent
    speckle of mixed round and faceted grains at this geometry (:mod:`pwf_dask.physics.diffusers`)
    over a grid of median grain radii, or white speckle; the template of least chi^2 wins.
    Sharp-edged grains give C a power-law tail that a Gaussian cannot imitate: that is what
    separates the two factors, and a diffuser of smooth blobs would still read long. The
    lengths exclude the detector pixel's blur (the templates carry it), so PWF models pixel
    integration on top. Below :data:`LOW_DOSE_PHOTONS` photons a pixel the fitted frequencies
    are chosen on the smoothed spectrum (:func:`fit_selection_spectrum`). ``method="gaussian"``:
    the Gaussian flank fit alone
    (:func:`_gaussian_flank_lengths`), also what is used without the geometry.
    """
    img = to_numpy(reference).astype(np.float64)
    if img.ndim != 2 or min(img.shape) < 32:
        raise ValueError(f"reference must be a 2-D image of at least 32 x 32 pixels, got shape {img.shape}")
    if method not in COHERENCE_METHODS:
        raise ValueError(f"unknown coherence method {method!r}: choose one of {', '.join(COHERENCE_METHODS)}")
    if method == "gaussian" or energy_eV is None or diffuser_detector_distance_m is None:
        x, y = _gaussian_flank_lengths(img, pixel_size_m)
        return CoherenceFit(x, y, "gaussian")
    mean = float(img.mean())
    if not mean > 0:
        raise ValueError("reference has zero mean intensity")
    img = img / mean
    tile = spectrum_tile(img.shape)
    spectrum, variance = speckle_spectrum(img, tile)
    noise = white_noise_floor(img)
    selection = fit_selection_spectrum(spectrum, noise)
    geometry = (tile, float(pixel_size_m), float(energy_eV), float(diffuser_detector_distance_m), diffuser_material)
    fits: dict[tuple[str, float | None], tuple | None] = {}

    def fit_grains(radii) -> None:
        for radius, template in zip(radii, _template_spectra(geometry, radii)):
            fits[("mixed grains", radius)] = _fit_iotf(spectrum, variance, noise, template, selection)

    def chi2(key) -> float:
        found = fits[key]
        return math.inf if found is None else found[2]

    radii = template_radii_m(pixel_size_m)
    fit_grains(radii)
    best = min(fits, key=chi2)
    if fits[best] is not None and best[1] < TEMPLATE_REFINE_BELOW_PX * pixel_size_m:
        k = 2 * TEMPLATE_RADII_M.index(best[1])  # on the 2^(1/4) grid
        fit_grains([r for r in (0.5e-6 * 2 ** ((k + j) / 4) for j in (-1, 1)) if radii[0] <= r <= radii[-1]])
    # delta-correlated speckle (the Siegert premise) as a detector pixel sees it
    fits[("white", None)] = _fit_iotf(spectrum, variance, noise, _pixel_transfer_squared(tile), selection)
    best = min(fits, key=chi2)
    if fits[best] is None:
        raise ValueError(
            f"coherence-length fit failed: {_unresolved_blur_reason(spectrum, noise, selection)}; "
            "give coherence_length_x_m and coherence_length_y_m explicitly"
        )
    x_px, y_px, best_chi2, points = fits[best]
    return CoherenceFit(
        x_m=x_px * pixel_size_m,
        y_m=y_px * pixel_size_m,
        method="template",
        template=best[0],
        grain_radius_m=best[1],
        chi2_per_point=best_chi2 / points,
        points=points,
        reference_photons_per_px=1.0 / noise if noise > 0 else None,  # None: no photon noise read
    )


def _unresolved_blur_reason(spectrum: np.ndarray, noise: float, selection: np.ndarray) -> str:
    """Why no IOTF could be fitted, in the user's terms: speckle up to the Nyquist frequency
    (a blur under about a pixel: the corners the noise floor is read from hold speckle too),
    or too few frequencies above the noise (speckle washed out, too few photons, or a frame
    too small). ``selection``: the spectrum the fit chose its frequencies on
    (:func:`fit_selection_spectrum`)."""
    ty, tx = spectrum.shape
    v, u = np.fft.fftfreq(ty)[:, None], np.fft.fftfreq(tx)[None, :]
    q = np.hypot(u, v)
    band = (q >= FIT_MIN_FREQUENCY) & (q < 0.5) & (u >= 0) & (v >= 0)  # the frequencies _fit_iotf reads
    above = int(np.sum(band & _above_noise(spectrum, selection, noise)))
    if float(np.mean(spectrum[(q >= 0.4) & (q < 0.5)])) > 1.3 * noise:
        return (
            "the reference's speckle reaches the Nyquist frequency, so its blur is under about a pixel "
            "and cannot be told from the photon noise"
        )
    return (
        f"{above} of the reference's frequencies stand {FIT_MIN_SIGNAL_TO_NOISE:g}x above its photon noise, "
        f"the fit needs {FIT_MIN_POINTS} "
        f"(speckle washed out, too few photons, or a frame too small: "
        f"{spectrum.shape[0]} x {spectrum.shape[1]} px tiles)"
    )


def coherence_lengths(reference, pixel_size_m: float, **options) -> tuple[float, float]:
    """(x_coh, y_coh) in metres from the reference speckle: :func:`fit_coherence_lengths`
    with the same keyword options, its lengths alone."""
    fit = fit_coherence_lengths(reference, pixel_size_m, **options)
    return fit.x_m, fit.y_m


def noise_to_signal(reference_spectrum_power, pixel_radius2, iotf_half, noise_per_bin: float = 0.0) -> float:
    """Scalar noise-to-signal ratio of the Wiener filter.

    White noise fills the spectrum beyond the Nyquist circle (u^2 + v^2 > 1/4 cycles/pixel^2,
    the corners), where the IOTF has removed any speckle; the coherent signal power is what
    the low-frequency band holds above that floor, corrected for the IOTF there.
    ``noise_per_bin`` > 0: another image's noise on this spectrum's scale (the sample image's,
    :func:`relative_noise_variance` times the grid's pixels), taken where it is the larger:
    the ratio the reference's speckle has at that image's noise.
    """
    xp = get_array_module(reference_spectrum_power)
    corners = pixel_radius2 > 0.25
    noise = float(xp.mean(reference_spectrum_power[corners])) if bool(xp.any(corners)) else 0.0
    if iotf_half is None:
        return 0.0
    band = (iotf_half > 0.5) & (pixel_radius2 > 0)
    if not bool(xp.any(band)):
        return 0.0
    signal = float(xp.mean((reference_spectrum_power[band] - noise) / iotf_half[band] ** 2))
    if signal <= 0:
        return 1.0
    return max(noise, noise_per_bin) / signal


def relative_noise_variance(image) -> float:
    """The white photon noise's variance per pixel over the image's mean squared: 1 / photons
    per pixel for Poisson counts, whatever the units (flat-corrected, attenuated by a sample,
    averaged from many flats). :func:`white_noise_floor` of the image over its mean; 0 for an
    image of no mean."""
    xp = get_array_module(image)
    img = xp.asarray(image, dtype=xp.float64)
    mean = float(img.mean())
    return white_noise_floor(img / mean) if mean > 0 else 0.0
