"""Simulated speckle projections with known ground truth, as realistic as the checks demand.

A projection is computed on a grid ``oversample`` times finer than the detector and wider
by ``margin_px`` detector pixels each side (so periodic wrap-around never reaches the frame):

1. sample: analytic phantom, exact chord lengths through a cylinder and spheres, delta and
   beta from xraydb, field exp(-i k delta L - k beta L) (the exp(+ikz) convention);
2. propagation over L1 (angular spectrum; skipped when L1 = 0);
3. the paper's diffuser by default: four layers of P3000 sandpaper, silicon-carbide grains
   6.5 um across with a FEPA-like spread of sizes (:mod:`pwf_dask.physics.diffusers`; other grits and
   grain shapes as options), a thin-object transmission;
   (or, with ``diffuser_upstream_m``, the diffuser before the sample: diffuser, free space,
   sample, the geometry the algorithms see as L1 = 0);
4. propagation over L2, intensity, partial-coherence blur by the IPSF, Eq. (IPSF), or
   (``coherence_model="source"``) an extended Gaussian source's incoherent sum over its
   points, which also moves the sample against the speckle (:mod:`pwf_dask.physics.source`);
5. optionally the detector's own blur (``detector_blur_fwhm_m``, ``detector_halo_fraction``:
   :func:`pwf_dask.physics.optics.detector_transfer_function`), which the paper's model lacks;
6. detector pixel integration (block mean), Poisson noise at ``photons`` per pixel.

The reference is the same without the sample (independent noise). Ground truth phase and
attenuation are the pixel means of the fine-grid line integrals.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pwf_dask.backend import FFT
from pwf_dask.calibration import shift_transmission
from pwf_dask.physics import diffusers, optics, source
from pwf_dask.physics.geometry import GEOMETRY_KEYS
from pwf_dask.physics.materials import delta_beta
from pwf_dask.simulation.phantoms import Phantom, default_phantom


def _geometry(obj) -> dict:
    return {name: getattr(obj, name) for name in GEOMETRY_KEYS}


@dataclass
class SimulatedProjection:
    """Flat/dark-corrected sample and reference images with the truth behind them."""

    sample: np.ndarray
    reference: np.ndarray
    phase: np.ndarray  # true Im(psi), rad
    attenuation: np.ndarray  # true -Re(psi)
    energy_eV: float
    pixel_size_m: float
    sample_diffuser_distance_m: float
    diffuser_detector_distance_m: float
    coherence_length_x_m: float
    coherence_length_y_m: float
    photons: float
    phantom: Phantom | None = None
    extras: dict = field(default_factory=dict)

    def geometry(self) -> dict:
        """The keyword arguments :func:`pwf_dask.retrieve_projection` needs for these images."""
        return _geometry(self)


#: ``SpeckleSetup`` fields of the finer sandpaper simulated before the paper's grit became the
#: default (grains of 1.2 um median radius, spread 0.6: many below the 0.65 um pixel). Its
#: speckle is finer than the coherence length, so PWF stays on the detector grid and the
#: Siegert fit's premise nearly holds; tests of a geometry or a detector defect use it to stay
#: fast, and the stability map's grain axis sweeps from it to coarser grits.
FINE_DIFFUSER = {"diffuser_radius_median_m": 1.2e-6, "diffuser_radius_spread": 0.6}


#: :attr:`SpeckleSetup.coherence_model`'s choices
COHERENCE_MODELS = ("detector", "source")


@dataclass
class SpeckleSetup:
    """Geometry and source of a simulated speckle measurement (defaults: the paper's set-up)."""

    shape: tuple[int, int] = (512, 512)
    energy_eV: float = 10_000.0
    pixel_size_m: float = 0.65e-6
    sample_diffuser_distance_m: float = 3e-3
    diffuser_detector_distance_m: float = 20e-3
    coherence_length_x_m: float = 3.47e-6
    coherence_length_y_m: float = 4.31e-6
    photons: float = 1e4
    oversample: int = 2
    margin_px: int = 32
    #: the paper's diffuser (Methods): four layers of P3000 silicon-carbide sandpaper
    diffuser_layers: int = diffusers.DEFAULT_LAYERS
    diffuser_material: str = diffusers.DEFAULT_MATERIAL
    #: a FEPA P grade (:data:`pwf_dask.physics.diffusers.FEPA_P_GRIT_DIAMETER_M`) setting the median grain
    #: radius, unless ``diffuser_radius_median_m`` gives it directly
    diffuser_grit: str = diffusers.DEFAULT_GRIT
    diffuser_radius_median_m: float | None = None
    diffuser_radius_spread: float = diffusers.FEPA_SPREAD
    diffuser_grain_shape: str = "spheres"  # or "faceted", "mixed" (:data:`pwf_dask.physics.diffusers.GRAIN_SHAPES`)
    rotation_axis_offset_m: float = 0.0
    #: > 0: the diffuser sits this far *upstream* of the sample instead of downstream. The
    #: algorithms then see L1 = 0 and L2 = the sample-detector distance
    #: (``diffuser_detector_distance_m``); the reference is the diffuser over both distances.
    diffuser_upstream_m: float = 0.0
    #: the detector's point-spread function (scintillator, microscope), on the intensity before
    #: the pixels: a Gaussian core of this FWHM, convolved with a halo holding
    #: ``detector_halo_fraction`` of the light over an exponential of 1/e radius
    #: ``detector_halo_radius_m`` (:func:`pwf_dask.physics.optics.detector_transfer_function`)
    detector_blur_fwhm_m: float = 0.0
    detector_halo_fraction: float = 0.0
    detector_halo_radius_m: float = 0.0
    #: how partial coherence enters: ``"detector"``, the paper's IPSF on the detector intensity
    #: (Eq. (IPSF), the model PWF fits), or ``"source"``, an extended Gaussian source whose
    #: tilted waves also move the sample against the speckle (:mod:`pwf_dask.physics.source`;
    #: the coherence lengths are then the reference's, at the diffuser's distance)
    coherence_model: str = "detector"
    #: nodes per axis of the source's angles (``"source"``; None: :func:`~pwf_dask.physics.source.nodes_per_axis`)
    source_nodes: int | None = None

    def geometry(self) -> dict:
        """The keyword arguments :func:`pwf_dask.retrieve_projection` needs for this set-up."""
        return _geometry(self)

    def blurred_coherence_lengths_m(self) -> tuple[float, float]:
        """(x, y) coherence lengths of the source and the detector's Gaussian core together: what
        a calibration from the reference should read (a halo aside)."""
        return (
            optics.blurred_coherence_length_m(self.coherence_length_x_m, self.detector_blur_fwhm_m),
            optics.blurred_coherence_length_m(self.coherence_length_y_m, self.detector_blur_fwhm_m),
        )

    def __post_init__(self):
        if self.diffuser_radius_median_m is None:
            self.diffuser_radius_median_m = diffusers.grit_radius_m(self.diffuser_grit)
        if self.diffuser_grain_shape not in diffusers.GRAIN_SHAPES:
            raise ValueError(
                f"unknown diffuser_grain_shape {self.diffuser_grain_shape!r}: choose one of "
                f"{', '.join(diffusers.GRAIN_SHAPES)}"
            )
        if self.diffuser_upstream_m < 0:
            raise ValueError(f"diffuser_upstream_m must be >= 0, got {self.diffuser_upstream_m}")
        if self.diffuser_upstream_m > 0 and self.sample_diffuser_distance_m != 0:
            raise ValueError(
                "a diffuser upstream of the sample needs sample_diffuser_distance_m = 0 (L1 = 0), got "
                f"{self.sample_diffuser_distance_m}"
            )
        optics.check_detector_blur(self.detector_blur_fwhm_m, self.detector_halo_fraction, self.detector_halo_radius_m)
        if self.coherence_model not in COHERENCE_MODELS:
            raise ValueError(
                f"unknown coherence_model {self.coherence_model!r}: choose one of {', '.join(COHERENCE_MODELS)}"
            )
        if self.source_nodes is not None and not (isinstance(self.source_nodes, int) and self.source_nodes >= 1):
            raise ValueError(f"source_nodes must be a whole number >= 1, got {self.source_nodes!r}")

    def fine_grid(self):
        s = self.oversample
        ny, nx = self.shape
        m = self.margin_px
        p = self.pixel_size_m
        fine = ((ny + 2 * m) * s, (nx + 2 * m) * s)

        # detector pixel i has centre (i - (n-1)/2) p - offset; fine pixels subdivide it
        def axis(n, nf, offset):
            j = np.arange(nf)
            return ((j + 0.5) / s - m - 0.5 - (n - 1) / 2) * p - offset

        x = axis(nx, fine[1], self.rotation_axis_offset_m)
        y = axis(ny, fine[0], 0.0)
        return fine, x, y


def dark_field_blur(intensity: np.ndarray, sigma_px: np.ndarray, levels: int = 9) -> np.ndarray:
    """``intensity`` under a Gaussian blur whose sigma (pixels of that grid) varies over it.

    Small-angle scattering by structure below the resolution (pores and fibres of wood or
    cork) spreads the beam over angles; behind the diffuser a tilt moves the speckle by the
    angle times L2, so the sample's footprint sees its speckle blurred and less visible: the
    dark-field signal, which UMPA's and MIST's models carry and PWF's does not. The blur is
    interpolated linearly between ``levels`` uniform ones (periodic, as the grid is).
    """
    from scipy import ndimage

    top = float(np.max(sigma_px))
    if top <= 0:
        return intensity
    pos = np.clip(np.asarray(sigma_px) / top * (levels - 1), 0.0, levels - 1)
    low = np.minimum(np.floor(pos).astype(int), levels - 2)
    frac = pos - low
    out = np.zeros_like(intensity)
    for j, sigma in enumerate(np.linspace(0.0, top, levels)):
        weight = np.where(low == j, 1.0 - frac, 0.0) + np.where(low == j - 1, frac, 0.0)
        if weight.any():
            out += weight * (ndimage.gaussian_filter(intensity, sigma, mode="wrap") if sigma else intensity)
    return out


def source_geometry(setup: SpeckleSetup) -> tuple[float, float]:
    """(z_ref, h) of :mod:`pwf_dask.physics.source`: the diffuser's distance to the detector,
    and the sample's shift against the speckle per radian of tilt."""
    if setup.diffuser_upstream_m:
        return setup.diffuser_upstream_m + setup.diffuser_detector_distance_m, -setup.diffuser_upstream_m
    return setup.diffuser_detector_distance_m, setup.sample_diffuser_distance_m


def sample_shift_sigma_m(setup: SpeckleSetup) -> tuple[float, float]:
    """The rms shift (y, x) of the sample against the speckle over the source's points: zero
    under the paper's IPSF model, at full coherence, or with both in one plane."""
    if setup.coherence_model != "source":
        return (0.0, 0.0)
    z_ref, h = source_geometry(setup)
    lengths = (setup.coherence_length_y_m, setup.coherence_length_x_m)
    return tuple(source.ipsf_sigma_m(c) * h / z_ref for c in lengths)


class SpeckleSimulator:
    """Forward simulation of sample and reference speckle images for one set-up and diffuser.

    The diffuser is drawn once (``seed``); :meth:`project` may be called for many angles, and
    ``diffuser_shift_px`` moves the diffuser laterally (the K positions of a scan).
    """

    def __init__(self, setup: SpeckleSetup | None = None, seed: int = 0):
        self.setup = setup or SpeckleSetup()
        st = self.setup
        self.rng = np.random.default_rng(seed)
        self.fine_shape, self.x, self.y = st.fine_grid()
        self.spacing = st.pixel_size_m / st.oversample
        self.wavelength = optics.wavelength_m(st.energy_eV)
        self.k = 2 * np.pi / self.wavelength
        self.fft = FFT.for_module(np)
        # diffuser larger than the frame so it can be shifted for K positions
        thick = diffusers.grain_thickness(
            self.fine_shape,
            self.spacing,
            self.rng,
            radius_median_m=st.diffuser_radius_median_m,
            radius_spread=st.diffuser_radius_spread,
            layers=st.diffuser_layers,
            grain_shape=st.diffuser_grain_shape,
        )
        d, b = delta_beta(st.diffuser_material, st.energy_eV)
        self.diffuser_thickness = thick
        self._delta_beta_diffuser = (d, b)
        self.kernel1 = (
            optics.angular_spectrum_kernel(
                self.fine_shape, self.spacing, self.wavelength, st.sample_diffuser_distance_m, np, np.complex128
            )
            if st.sample_diffuser_distance_m
            else None
        )
        self.kernel2 = optics.angular_spectrum_kernel(
            self.fine_shape, self.spacing, self.wavelength, st.diffuser_detector_distance_m, np, np.complex128
        )
        self.kernel_upstream = (
            optics.angular_spectrum_kernel(
                self.fine_shape, self.spacing, self.wavelength, st.diffuser_upstream_m, np, np.complex128
            )
            if st.diffuser_upstream_m
            else None
        )
        self._illumination = None  # (diffuser, its field at the sample) for the upstream geometry
        self.iotf = optics.iotf(
            self.fine_shape, self.spacing, st.coherence_length_x_m, st.coherence_length_y_m, np, np.float64
        )
        self.detector_transfer = optics.detector_transfer_function(
            self.fine_shape,
            self.spacing,
            st.detector_blur_fwhm_m,
            st.detector_halo_fraction,
            st.detector_halo_radius_m,
            np,
            np.float64,
        )

    def diffuser(self, shift_px: tuple[float, float] = (0, 0)) -> np.ndarray:
        """The diffuser's transmission moved laterally by ``shift_px`` (dy, dx) detector pixels:
        exact rolls on the fine grid where the shift is a whole number of fine pixels, a
        Fourier shift of the thickness (clipped at zero) where it is not (a drift)."""
        d, b = self._delta_beta_diffuser
        th = self.diffuser_thickness
        fine = np.asarray(shift_px, float) * self.setup.oversample
        if np.any(fine != 0):
            whole = np.round(fine)
            if np.allclose(fine, whole, atol=1e-9):
                th = np.roll(th, (int(whole[0]), int(whole[1])), axis=(0, 1))
            else:
                moved = shift_transmission(th.astype(np.complex128), (fine[0], fine[1]), self.fft)
                th = np.clip(moved.real, 0.0, None)
        return np.exp((-1j * d - b) * self.k * th)

    def _bin(self, a: np.ndarray) -> np.ndarray:
        st = self.setup
        s, m = st.oversample, st.margin_px
        ny, nx = st.shape
        a = a.reshape(a.shape[0] // s, s, a.shape[1] // s, s).mean(axis=(1, 3))
        return a[m : m + ny, m : m + nx]

    def intensity(
        self, sample_field: np.ndarray | None, diffuser: np.ndarray, dark_field_sigma_px: np.ndarray | None = None
    ) -> np.ndarray:
        """Noise-free detector intensity (flat = 1) for a fine-grid sample field (None: reference).

        ``dark_field_sigma_px``: the sample's small-angle scattering, a fine-grid map of the
        speckle blur sigma in detector pixels (:func:`dark_field_blur`); None: none.
        """
        fft = self.fft
        carrier, lit = self._carrier_and_sample(sample_field, diffuser)
        if sample_field is not None and sample_shift_sigma_m(self.setup) != (0.0, 0.0):
            inten = self._extended_source_intensity(carrier, lit)
        else:
            v = fft.ifft2(fft.fft2(carrier * lit) * self.kernel2)
            inten = np.abs(v) ** 2
            if self.iotf is not None:
                inten = fft.irfft2(fft.rfft2(inten) * self.iotf, s=self.fine_shape)
        if dark_field_sigma_px is not None:
            inten = dark_field_blur(inten, dark_field_sigma_px * self.setup.oversample)
        if self.detector_transfer is not None:
            # the scintillator sees the X-ray intensity as the sample and source left it
            inten = fft.irfft2(fft.rfft2(inten) * self.detector_transfer, s=self.fine_shape)
        return self._bin(inten)

    def _carrier_and_sample(self, sample_field, diffuser):
        """(the diffuser's field where the sample is, the sample's field there): their product
        goes over L2. Upstream, diffuser -> free space -> sample; else sample -> L1 -> diffuser."""
        fft = self.fft
        if self.kernel_upstream is not None:
            # the sample is lit by developed speckle, the same for every angle of a position,
            # so it is propagated once per diffuser
            if self._illumination is None or self._illumination[0] is not diffuser:
                self._illumination = (diffuser, fft.ifft2(fft.fft2(diffuser) * self.kernel_upstream))
            carrier = self._illumination[1]
            return carrier, (1.0 if sample_field is None else sample_field)
        if sample_field is None:
            return diffuser, 1.0
        if self.kernel1 is None:
            return diffuser, sample_field
        return diffuser, fft.ifft2(fft.fft2(sample_field) * self.kernel1)

    def _extended_source_intensity(self, carrier, lit):
        """The mean over the source's points of S[theta z_ref] |P2{t S[theta h] x}|^2
        (:mod:`pwf_dask.physics.source`), on the fine grid before the detector."""
        st, fft = self.setup, self.fft
        shift_sigma = sample_shift_sigma_m(self.setup)
        detector_sigma = [source.ipsf_sigma_m(c) for c in (st.coherence_length_y_m, st.coherence_length_x_m)]
        fy = np.fft.fftfreq(self.fine_shape[0], self.spacing)
        fx = np.fft.fftfreq(self.fine_shape[1], self.spacing)
        fx_half = np.fft.rfftfreq(self.fine_shape[1], self.spacing)
        n = [st.source_nodes or source.nodes_per_axis(s, st.pixel_size_m) for s in shift_sigma]
        nodes = [source.source_nodes(k) for k in n]
        transfer_y = source.node_transfer(fy, detector_sigma[0], n[0])
        transfer_x = source.node_transfer(fx_half, detector_sigma[1], n[1])
        spec_lit = fft.fft2(lit)  # the sample's field: this path runs only with one
        total = np.zeros((self.fine_shape[0], len(fx_half)), complex)
        for i, cy in enumerate(nodes[0]):
            ramp_y = source.shift_ramp(fy, cy * shift_sigma[0])[:, None]
            for j, cx in enumerate(nodes[1]):
                ramp_x = source.shift_ramp(fx, cx * shift_sigma[1])[None, :]
                a = fft.ifft2(spec_lit * ramp_y * ramp_x) * carrier
                v = fft.ifft2(fft.fft2(a) * self.kernel2)
                total += fft.rfft2(np.abs(v) ** 2) * (transfer_y[i][:, None] * transfer_x[j][None, :])
        return fft.irfft2(total, s=self.fine_shape)

    def dark_field_sigma_px(self, psi: np.ndarray, dark_field_px: float) -> np.ndarray | None:
        """The speckle blur map of a sample (fine grid, detector pixels): ``dark_field_px``
        behind its thickest part, growing as the square root of the projected thickness (the
        angular spread of multiple small-angle scattering), the phase standing for thickness."""
        if not dark_field_px:
            return None
        thick = np.abs(psi.imag)
        return dark_field_px * np.sqrt(thick / thick.max()) if thick.max() > 0 else None

    def sample_field(self, phantom: Phantom, angle_deg: float = 0.0):
        d_int, b_int = phantom.line_integrals(angle_deg, self.x, self.y, self.setup.energy_eV)
        psi = self.k * (-b_int - 1j * d_int)
        return np.exp(psi), psi

    def noisy(self, intensity: np.ndarray, photons: float | None = None) -> np.ndarray:
        p = self.setup.photons if photons is None else photons
        if not np.isfinite(p):
            return intensity.astype(np.float32)
        return (self.rng.poisson(np.clip(intensity, 0, None) * p) / p).astype(np.float32)

    def project(
        self, phantom: Phantom, angle_deg: float = 0.0, shift_px=(0, 0)
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(noisy sample image, true phase, true attenuation) at one angle."""
        field_, psi = self.sample_field(phantom, angle_deg)
        img = self.noisy(self.intensity(field_, self.diffuser(shift_px)))
        return img, self._bin(psi.imag), self._bin(-psi.real)

    def reference(self, shift_px=(0, 0)) -> np.ndarray:
        return self.noisy(self.intensity(None, self.diffuser(shift_px)))


def simulate_projection(
    setup: SpeckleSetup | None = None,
    phantom: Phantom | None = None,
    angle_deg: float = 0.0,
    seed: int = 0,
) -> SimulatedProjection:
    """One sample image and one reference with the true phase and attenuation.

    Defaults: the paper's geometry (10 keV, 0.65 um pixels, L1 = 3 mm, L2 = 20 mm, coherence
    lengths 3.47 / 4.31 um) on a 512 x 512 detector at 1e4 photons per pixel, and the
    default toothpick-and-beads phantom scaled to the field of view.
    """
    setup = setup or SpeckleSetup()
    sim = SpeckleSimulator(setup, seed=seed)
    if phantom is None:
        fov = setup.shape[1] * setup.pixel_size_m
        phantom = default_phantom(fov, np.random.default_rng(seed + 1), height_m=setup.shape[0] * setup.pixel_size_m)
    img, phase, att = sim.project(phantom, angle_deg)
    ref = sim.reference()
    return SimulatedProjection(
        sample=img,
        reference=ref,
        phase=phase,
        attenuation=att,
        energy_eV=setup.energy_eV,
        pixel_size_m=setup.pixel_size_m,
        sample_diffuser_distance_m=setup.sample_diffuser_distance_m,
        diffuser_detector_distance_m=setup.diffuser_detector_distance_m,
        coherence_length_x_m=setup.coherence_length_x_m,
        coherence_length_y_m=setup.coherence_length_y_m,
        photons=setup.photons,
        phantom=phantom,
        extras={"setup": setup},
    )
