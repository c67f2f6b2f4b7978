"""Simulated speckle projections with known ground truth, as realistic as the checks demand.

A projection is computed on a grid ``oversample`` times finer than the detector and wider
by ``margin_px`` detector pixels each side (so periodic wrap-around never reaches the frame):

1. sample: analytic phantom, exact chord lengths through a cylinder and spheres, delta and
   beta from xraydb, field exp(-i k delta L - k beta L) (the exp(+ikz) convention);
2. propagation over L1 (angular spectrum; skipped when L1 = 0);
3. the paper's diffuser by default: four layers of P3000 sandpaper, silicon-carbide grains
   6.5 um across with a FEPA-like spread of sizes (:mod:`pwf_dask.diffusers`; other grits and
   grain shapes as options), a thin-object transmission;
   (or, with ``diffuser_upstream_m``, the diffuser before the sample: diffuser, free space,
   sample, the geometry the algorithms see as L1 = 0);
4. propagation over L2, intensity, partial-coherence blur by the IPSF, Eq. (IPSF);
5. detector pixel integration (block mean), Poisson noise at ``photons`` per pixel.

The reference is the same without the sample (independent noise). Ground truth phase and
attenuation are the pixel means of the fine-grid line integrals.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, replace

import numpy as np

from . import diffusers, optics
from .backend import FFT
from .calibration import shift_transmission
from .materials import delta_beta
from .progress import Progress


@dataclass(frozen=True)
class Sphere:
    """A sphere (bead) at (u, y, v) metres in the sample frame."""

    u_m: float
    y_m: float
    v_m: float
    radius_m: float
    material: str = "soda-lime glass"


@dataclass(frozen=True)
class Phantom:
    """A vertical cylinder (axis along y at (u, v)) with spheres embedded in it.

    Spheres lie inside the cylinder (their material replaces the cylinder's along their
    chord) or outside it entirely; the projected delta/beta sums are then exact.
    """

    cylinder_radius_m: float = 120e-6
    cylinder_u_m: float = 0.0
    cylinder_v_m: float = 0.0
    cylinder_material: str = "cellulose"
    spheres: tuple[Sphere, ...] = ()

    def line_integrals(self, angle_deg: float, x_m: np.ndarray, y_m: np.ndarray, energy_eV: float):
        """(integral of delta, integral of beta) along the beam, in metres, on the (y, x) grid.

        A detector pixel at angle theta sees the line x = u cos(theta) + v sin(theta) (CONTRACT §2).
        """
        th = np.deg2rad(angle_deg)
        c, s = np.cos(th), np.sin(th)
        xx = x_m[None, :]
        yy = y_m[:, None]
        dc, bc = delta_beta(self.cylinder_material, energy_eV)
        xc = self.cylinder_u_m * c + self.cylinder_v_m * s
        chord = 2.0 * np.sqrt(np.clip(self.cylinder_radius_m**2 - (xx - xc) ** 2, 0, None))
        chord = np.broadcast_to(chord, (y_m.size, x_m.size))
        d_int = dc * chord
        b_int = bc * chord
        for sp in self.spheres:
            ds, bs = delta_beta(sp.material, energy_eV)
            xs = sp.u_m * c + sp.v_m * s
            ch = 2.0 * np.sqrt(np.clip(sp.radius_m**2 - (xx - xs) ** 2 - (yy - sp.y_m) ** 2, 0, None))
            inside = np.hypot(sp.u_m - self.cylinder_u_m, sp.v_m - self.cylinder_v_m) < self.cylinder_radius_m
            d_int = d_int + (ds - (dc if inside else 0.0)) * ch
            b_int = b_int + (bs - (bc if inside else 0.0)) * ch
        return d_int, b_int


@dataclass(frozen=True)
class Rods:
    """Parallel vertical rods of one material (axes along y at (u, v)), nothing inside them.

    The regime of issue #27's real scan: mm-wide PMMA rods across a wide strip, one of them
    cut by the frame's edge. Projections only (:meth:`line_integrals`); no volume truth.
    """

    u_m: tuple[float, ...]
    radii_m: tuple[float, ...]
    v_m: tuple[float, ...] | None = None
    material: str = "PMMA"
    spheres: tuple[Sphere, ...] = ()  # none: the simulator's phantom protocol

    def line_integrals(self, angle_deg: float, x_m: np.ndarray, y_m: np.ndarray, energy_eV: float):
        """(integral of delta, integral of beta) in metres on the (y, x) grid: exact chords."""
        th = np.deg2rad(angle_deg)
        d, b = delta_beta(self.material, energy_eV)
        vs = self.v_m or (0.0,) * len(self.u_m)
        chord = np.zeros(x_m.size)
        for u, v, r in zip(self.u_m, vs, self.radii_m, strict=True):
            xc = u * np.cos(th) + v * np.sin(th)
            chord += 2.0 * np.sqrt(np.clip(r * r - (x_m - xc) ** 2, 0, None))
        chord = np.broadcast_to(chord[None, :], (y_m.size, x_m.size))
        return d * chord, b * chord


def default_phantom(
    field_of_view_m: float,
    rng: np.random.Generator | None = None,
    n_beads: int = 6,
    height_m: float | None = None,
    cylinder_fraction: float = 0.72,
    bead_radius_range_m: tuple[float, float] | None = None,
) -> Phantom:
    """A toothpick-like cellulose cylinder with soda-lime glass beads inside it (the paper's sample).

    Sizes scale with the field of view: the cylinder spans ``cylinder_fraction`` of it, bead
    radii 5-12 % of it (at most 40 % of the frame height), beads placed without overlap inside
    the cylinder and the frame height.
    """
    rng = rng or np.random.default_rng(0)
    height_m = height_m or field_of_view_m
    big_r = 0.5 * cylinder_fraction * field_of_view_m
    lo, hi = bead_radius_range_m or (0.05 * field_of_view_m, 0.12 * field_of_view_m)
    # a frame of few rows (a slab of a wide detector) holds smaller beads: each must fit
    # its height with the 1.2 r margin the placement keeps
    hi = min(hi, 0.5 * height_m / 1.25)
    # and inside the cylinder, with the 1.05 r margin the placement keeps
    hi = min(hi, big_r / 1.1)
    lo = min(lo, hi)
    spheres: list[Sphere] = []
    radii = np.sort(rng.uniform(lo, hi, n_beads))[::-1]
    radii[0] = hi
    for r in radii:
        for _ in range(2000):
            rho = rng.uniform(0, big_r - r * 1.05)
            ang = rng.uniform(0, 2 * np.pi)
            u, v = rho * np.cos(ang), rho * np.sin(ang)
            y = rng.uniform(-0.5 * height_m + r * 1.2, 0.5 * height_m - r * 1.2)
            if all(
                np.sqrt((u - o.u_m) ** 2 + (v - o.v_m) ** 2 + (y - o.y_m) ** 2) > r + o.radius_m + 2e-6 for o in spheres
            ):
                spheres.append(Sphere(u, y, v, float(r)))
                break
    return Phantom(cylinder_radius_m=big_r, spheres=tuple(spheres))


def _geometry(obj) -> dict:
    return {name: getattr(obj, name) for name in GEOMETRY_KEYS}


#: what :func:`pwf_dask.retrieve_projection` must be told about a measurement
GEOMETRY_KEYS = ("energy_eV", "pixel_size_m", "sample_diffuser_distance_m", "diffuser_detector_distance_m")


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
    #: a FEPA P grade (:data:`pwf_dask.diffusers.FEPA_P_GRIT_DIAMETER_M`) setting the median grain
    #: radius, unless ``diffuser_radius_median_m`` gives it directly
    diffuser_grit: str = diffusers.DEFAULT_GRIT
    diffuser_radius_median_m: float | None = None
    diffuser_radius_spread: float = diffusers.FEPA_SPREAD
    diffuser_grain_shape: str = "spheres"  # or "faceted", "mixed" (:data:`pwf_dask.diffusers.GRAIN_SHAPES`)
    rotation_axis_offset_m: float = 0.0
    #: > 0: the diffuser sits this far *upstream* of the sample instead of downstream. The
    #: algorithms then see L1 = 0 and L2 = the sample-detector distance
    #: (``diffuser_detector_distance_m``); the reference is the diffuser over both distances.
    diffuser_upstream_m: float = 0.0

    def geometry(self) -> dict:
        """The keyword arguments :func:`pwf_dask.retrieve_projection` needs for this set-up."""
        return _geometry(self)

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
        if self.kernel_upstream is not None:
            # diffuser -> free space -> sample -> L2: the sample is lit by developed speckle,
            # the same for every angle of a position, so it is propagated once per diffuser
            if self._illumination is None or self._illumination[0] is not diffuser:
                self._illumination = (diffuser, fft.ifft2(fft.fft2(diffuser) * self.kernel_upstream))
            a = self._illumination[1]
            if sample_field is not None:
                a = a * sample_field
        else:
            if sample_field is None:
                a = np.ones(self.fine_shape, complex)
            elif self.kernel1 is None:
                a = sample_field
            else:
                a = fft.ifft2(fft.fft2(sample_field) * self.kernel1)
            a = a * diffuser
        v = fft.ifft2(fft.fft2(a) * self.kernel2)
        inten = np.abs(v) ** 2
        if self.iotf is not None:
            inten = fft.irfft2(fft.rfft2(inten) * self.iotf, s=self.fine_shape)
        if dark_field_sigma_px is not None:
            inten = dark_field_blur(inten, dark_field_sigma_px * self.setup.oversample)
        return self._bin(inten)

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


# --- whole scans ---------------------------------------------------------------------------


def phantom_to_json(ph: Phantom) -> str:
    import json
    from dataclasses import asdict

    return json.dumps(asdict(ph))


def phantom_from_json(text: str) -> Phantom:
    import json

    d = json.loads(text)
    d["spheres"] = tuple(Sphere(**s) for s in d.get("spheres", ()))
    return Phantom(**d)


def refractive_index_volume(phantom: Phantom, y_m, v_m, u_m, energy_eV: float, supersample: int = 2):
    """True (delta, beta) on the (y, v, u) voxel grid, each voxel averaged over supersample^3 points."""
    y_m, v_m, u_m = (np.asarray(a, np.float64) for a in (y_m, v_m, u_m))
    dy = abs(y_m[1] - y_m[0]) if y_m.size > 1 else 1.0
    du = abs(u_m[1] - u_m[0])
    off = (np.arange(supersample) + 0.5) / supersample - 0.5
    dc, bc = delta_beta(phantom.cylinder_material, energy_eV)
    delta = np.zeros((y_m.size, v_m.size, u_m.size))
    beta = np.zeros_like(delta)
    for oy in off:
        for ov in off:
            for ou in off:
                yy = (y_m + oy * dy)[:, None, None]
                vv = (v_m + ov * du)[None, :, None]
                uu = (u_m + ou * du)[None, None, :]
                incyl = (
                    (uu - phantom.cylinder_u_m) ** 2 + (vv - phantom.cylinder_v_m) ** 2
                ) < phantom.cylinder_radius_m**2
                d = np.broadcast_to(np.where(incyl, dc, 0.0), delta.shape).copy()
                b = np.broadcast_to(np.where(incyl, bc, 0.0), delta.shape).copy()
                for sp in phantom.spheres:
                    ds, bs = delta_beta(sp.material, energy_eV)
                    ins = ((uu - sp.u_m) ** 2 + (vv - sp.v_m) ** 2 + (yy - sp.y_m) ** 2) < sp.radius_m**2
                    d = np.where(ins, ds, d)
                    b = np.where(ins, bs, b)
                delta += d
                beta += b
    n = supersample**3
    return delta / n, beta / n


#: the cylinder diameter of :func:`scan_phantom` over the frame width (0.8 x default_phantom's 0.72)
SCAN_CYLINDER_WIDTH_FRACTION = 0.8 * 0.72


#: radii of the paper's glass beads (Merck G8893, <= 106 um across; Methods, Samples): the
#: ``beads`` and ``paper`` presets draw their beads from this range, not from the frame's size
PAPER_BEAD_RADIUS_M = (25e-6, 53e-6)


def scan_phantom(
    shape: tuple[int, int],
    pixel_size_m: float,
    seed: int = 0,
    cylinder_width_fraction: float | None = None,
    bead_radius_range_m: tuple[float, float] | None = None,
) -> Phantom:
    """The phantom :func:`simulate_scan` draws for a frame of ``shape`` and its ``seed``: the
    cylinder spans :data:`SCAN_CYLINDER_WIDTH_FRACTION` of the width, one bead per 12 rows (>= 3).

    Bead radii are 5-12 % of the field of view unless ``bead_radius_range_m`` gives them in
    metres (e.g. :data:`PAPER_BEAD_RADIUS_M`); either way a bead fits the frame height and the
    cylinder, so a small frame holds smaller beads than asked for.

    ``cylinder_width_fraction`` widens (or narrows) the cylinder alone; the beads stay where
    the default draws them, inside the field of view. Above 1 the sample is wider than the
    field of view at every angle: an interior (local) scan.
    """
    ny, nx = shape
    phantom = default_phantom(
        0.8 * nx * pixel_size_m,
        np.random.default_rng(seed + 1000),
        height_m=ny * pixel_size_m,
        n_beads=max(3, ny // 12),
        bead_radius_range_m=bead_radius_range_m,
    )
    if cylinder_width_fraction is None:
        return phantom
    radius = 0.5 * cylinder_width_fraction * nx * pixel_size_m
    if any(np.hypot(s.u_m, s.v_m) + s.radius_m > radius for s in phantom.spheres):
        raise ValueError(
            f"cylinder_width_fraction {cylinder_width_fraction} is too small for the beads: use at least "
            f"{SCAN_CYLINDER_WIDTH_FRACTION:.3f}"
        )
    return replace(phantom, cylinder_radius_m=radius)


PRESETS: dict[str, dict] = {
    # a slab of the paper's scan (the default): glass beads of the paper's size (one of 83 um
    # across fills the 160 rows) at its 0.65 um pixel, so a bead's radius is ~12 coherence
    # lengths as in the paper; a few minutes on a laptop
    "beads": dict(shape=(160, 320), angles=121, positions=2, photons=1e4, bead_radius_m=PAPER_BEAD_RADIUS_M),
    # seconds on a laptop: what `pwf-dask demo` reconstructs. The phantom is the paper's
    # shrunk to 128 px: its beads are 12 px (2 coherence lengths) in radius, smaller than
    # the paper's, and PWF with the paper's alpha overshoots them (docs/validation.md, Where PWF fails)
    "demo": dict(shape=(48, 128), angles=61, positions=2, photons=1e4),
    # the demo's phantom on a larger frame: beads up to 18 px in radius
    "small": dict(shape=(64, 192), angles=121, positions=2, photons=1e4),
    # the paper's scan: 801 angles over 0-180 degrees of 2160 x 2560 pixels (~18 GB)
    "paper": dict(shape=(2160, 2560), angles=801, positions=1, photons=1e4, bead_radius_m=PAPER_BEAD_RADIUS_M),
}

#: what ``pwf-dask simulate`` (and :func:`simulate_scan`) draws when no preset is named
DEFAULT_PRESET = "beads"


def simulate_scan(
    path,
    *,
    preset: str = DEFAULT_PRESET,
    shape: tuple[int, int] | None = None,
    angles: int | None = None,
    positions: int | None = None,
    photons: float | None = None,
    seed: int = 0,
    raw: bool = True,
    rotation_axis_offset_px: float = 0.0,
    diffuser_upstream_m: float = 0.0,
    zingers: float = 0.0,
    diffuser_drift_px: tuple[float, float] = (0.0, 0.0),
    cylinder_width_fraction: float | None = None,
    dark_field_px: float = 0.0,
    diffuser_grit: str = diffusers.DEFAULT_GRIT,
    diffuser_radius_median_m: float | None = None,
    diffuser_grain_shape: str = "spheres",
    progress: bool = True,
) -> str:
    """Simulate a whole scan into a Zarr store (CONTRACT §1) and return its path.

    Angles span 0-180 degrees inclusive; each of the K positions is an independent diffuser
    realisation with its own reference. ``raw``: uint16 counts with a flat (a beam profile)
    and a dark frame, as a detector delivers them; else flat/dark-corrected float32. The rotation
    axis sits ``rotation_axis_offset_px`` from the frame centre (the tomography stage must
    find it). ``diffuser_upstream_m`` > 0 puts the diffuser that far upstream of the sample
    (the scan records L1 = 0). ``zingers`` is the fraction of pixels of every frame (sample and
    reference) hit by a zinger: one pixel gets 2-20x the open-beam counts on top (a scattered
    X-ray on the sensor; :mod:`pwf_dask.detector`). ``diffuser_drift_px`` = (dy, dx): the
    diffuser drifts linearly in time from where it was for the reference to that far (detector
    pixels) at the last angle (thermal drift; :func:`pwf_dask.calibration.speckle_drift_px`).
    ``cylinder_width_fraction``: the cylinder's diameter over the frame width (default
    :data:`SCAN_CYLINDER_WIDTH_FRACTION`); above 1 the scan is an interior scan
    (:func:`scan_phantom`). ``dark_field_px`` > 0: the sample scatters at small angles and
    blurs the speckle behind its thickest part by a Gaussian of that sigma (detector pixels;
    :func:`dark_field_blur`). The diffuser is four layers of ``diffuser_grit`` sandpaper (the
    paper's P3000 by default), or grains of ``diffuser_radius_median_m``, of
    ``diffuser_grain_shape`` (:mod:`pwf_dask.diffusers`). The phantom, the diffuser and the
    truth are recorded in the attributes.
    """
    from . import scan_io

    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    cfg = dict(PRESETS[preset])
    shape = tuple(shape or cfg["shape"])
    n_ang = int(angles or cfg["angles"])
    n_pos = int(positions or cfg["positions"])
    photons = float(photons or cfg["photons"])
    if n_ang < 2 or n_pos < 1 or min(shape) < 32 or photons <= 0:
        raise ValueError(
            f"simulate: need >= 2 angles, >= 1 position, >= 32 x 32 px, photons > 0; got "
            f"{n_ang}, {n_pos}, {shape}, {photons}"
        )
    drift = np.asarray(diffuser_drift_px, float)
    if drift.shape != (2,) or not np.all(np.isfinite(drift)):
        raise ValueError(f"simulate: diffuser_drift_px is a finite (dy, dx) pair, got {diffuser_drift_px!r}")
    if cylinder_width_fraction is not None and not 0 < cylinder_width_fraction <= 10:
        raise ValueError(f"simulate: cylinder_width_fraction is in (0, 10], got {cylinder_width_fraction}")
    if not 0 <= dark_field_px <= 20:
        raise ValueError(f"simulate: dark_field_px is a blur sigma in [0, 20] px, got {dark_field_px}")
    if not 0 <= zingers < 0.1:
        raise ValueError(f"simulate: zingers is a fraction of the pixels in [0, 0.1), got {zingers}")
    setup = SpeckleSetup(
        shape=shape,
        photons=photons,
        diffuser_grit=diffuser_grit,
        diffuser_radius_median_m=diffuser_radius_median_m,
        diffuser_grain_shape=diffuser_grain_shape,
    )
    if diffuser_upstream_m:
        setup = replace(setup, sample_diffuser_distance_m=0.0, diffuser_upstream_m=diffuser_upstream_m)
    p = setup.pixel_size_m
    setup.rotation_axis_offset_m = rotation_axis_offset_px * p
    phantom = scan_phantom(shape, p, seed, cylinder_width_fraction, cfg.get("bead_radius_m"))
    angles_deg = np.linspace(0.0, 180.0, n_ang)
    attrs = {
        "energy_eV": setup.energy_eV,
        "pixel_size_m": p,
        "sample_diffuser_distance_m": setup.sample_diffuser_distance_m,
        "diffuser_detector_distance_m": setup.diffuser_detector_distance_m,
        "flat_dark_corrected": not raw,
        "simulated": True,
        "simulation_preset": preset,
        "simulation_photons": photons,
        "simulation_seed": seed,
        "simulation_coherence_length_x_m": setup.coherence_length_x_m,
        "simulation_coherence_length_y_m": setup.coherence_length_y_m,
        "simulation_rotation_axis_offset_m": setup.rotation_axis_offset_m,
        "simulation_diffuser_upstream_m": setup.diffuser_upstream_m,
        "simulation_zingers": zingers,
        "simulation_dark_field_px": float(dark_field_px),
        "simulation_diffuser_grit": setup.diffuser_grit if diffuser_radius_median_m is None else "",
        "simulation_diffuser_radius_median_m": setup.diffuser_radius_median_m,
        "simulation_diffuser_grain_shape": setup.diffuser_grain_shape,
        "simulation_diffuser_drift_y_px": float(diffuser_drift_px[0]),
        "simulation_diffuser_drift_x_px": float(diffuser_drift_px[1]),
        "simulation_phantom": phantom_to_json(phantom),
    }
    dtype = "uint16" if raw else "float32"
    g = scan_io.create_scan(
        path,
        n_positions=n_pos,
        angles_deg=angles_deg,
        shape=shape,
        pixel_size_m=p,
        dtype=dtype,
        attrs=attrs,
        flat_dark=raw,
    )
    ny, nx = shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    beam = 1.0 - 0.15 * (((xx - nx / 2) / nx) ** 2 + ((yy - ny / 2) / ny) ** 2)  # flat-field profile
    dark_level = 100.0
    noise_rng = np.random.default_rng(seed + 7)
    if raw:
        g["flat"][...] = np.round(beam * photons + dark_level).astype(np.uint16)
        g["dark"][...] = np.full(shape, dark_level, np.uint16)

    # its own stream, so that a scan without zingers is the scan simulated before they existed
    zinger_rng = np.random.default_rng(seed + 13)
    n_zingers = int(round(zingers * ny * nx))

    def add_zingers(frame, level):
        hit = zinger_rng.choice(frame.size, n_zingers, replace=False)
        frame.flat[hit] += zinger_rng.uniform(2.0, 20.0, n_zingers) * level
        return frame

    def detect(intensity):
        if not raw:
            img = (noise_rng.poisson(np.clip(intensity, 0, None) * photons) / photons).astype(np.float32)
            return add_zingers(img, 1.0) if n_zingers else img
        counts = noise_rng.poisson(np.clip(intensity, 0, None) * beam * photons) + dark_level
        if n_zingers:
            counts = add_zingers(counts.astype(np.float64), photons)
        return np.clip(counts, 0, 65535).astype(np.uint16)

    written = [0]
    with contextlib.ExitStack() as stack:
        if progress:
            stack.enter_context(Progress("simulate", n_pos * n_ang, lambda: written[0], unit="projections"))
        for k in range(n_pos):
            sim = SpeckleSimulator(setup, seed=seed + 101 * k)
            t = sim.diffuser()
            g["reference"][k] = detect(sim.intensity(None, t))
            for a, ang in enumerate(angles_deg):
                fld, psi = sim.sample_field(phantom, float(ang))
                t_a = sim.diffuser(tuple(drift * a / (n_ang - 1))) if drift.any() else t
                g["projections"][k, a] = detect(sim.intensity(fld, t_a, sim.dark_field_sigma_px(psi, dark_field_px)))
                written[0] += 1
    scan_io.consolidate(path)
    return str(path)
