"""Simulated scans written as scan stores (docs/scan-format.md §1): presets, raw counts with flat and dark.

:func:`simulate_scan` draws a phantom (:mod:`~pwf_dask.simulation.phantoms`), simulates every
angle's speckle (:mod:`~pwf_dask.simulation.speckle`) and writes the store through
:mod:`pwf_dask.stores.scan_io`.
"""

from __future__ import annotations

import contextlib
from dataclasses import replace

import numpy as np

from pwf_dask.physics import diffusers
from pwf_dask.progress import Progress
from pwf_dask.simulation.phantoms import PAPER_BEAD_RADIUS_M, phantom_to_json, scan_phantom
from pwf_dask.simulation.speckle import SpeckleSetup, SpeckleSimulator

PRESETS: dict[str, dict] = {
    # a slab of the paper's scan (the default): glass beads of the paper's size (one of 83 um
    # across fills the 160 rows) at its 0.65 um pixel, so a bead's radius is ~12 coherence
    # lengths as in the paper; a few minutes on a laptop
    "beads": dict(shape=(160, 320), angles=121, positions=2, photons=1e4, bead_radius_m=PAPER_BEAD_RADIUS_M),
    # about two minutes on 2 cores: what `pwf-dask demo` reconstructs. The phantom is the paper's
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
    beads: bool = True,
    detector_blur_fwhm_m: float = 0.0,
    detector_halo: tuple[float, float] = (0.0, 0.0),
    optics: dict | None = None,
    coherence_model: str = "detector",
    progress: bool = True,
) -> str:
    """Simulate a whole scan into a Zarr store (docs/scan-format.md §1) and return its path.

    Angles span 0-180 degrees inclusive; each of the K positions is an independent diffuser
    realisation with its own reference. ``raw``: uint16 counts with a flat (a beam profile)
    and a dark frame, as a detector delivers them; else flat/dark-corrected float32. The rotation
    axis sits ``rotation_axis_offset_px`` from the frame centre (the tomography stage must
    find it). ``diffuser_upstream_m`` > 0 puts the diffuser that far upstream of the sample
    (the scan records L1 = 0). ``zingers`` is the fraction of pixels of every frame (sample and
    reference) hit by a zinger: one pixel gets 2-20x the open-beam counts on top (a scattered
    X-ray on the sensor; :mod:`pwf_dask.physics.detector`). ``diffuser_drift_px`` = (dy, dx): the
    diffuser drifts linearly in time from where it was for the reference to that far (detector
    pixels) at the last angle (thermal drift; :func:`pwf_dask.calibration.speckle_drift_px`).
    ``cylinder_width_fraction``: the cylinder's diameter over the frame width (default
    :data:`SCAN_CYLINDER_WIDTH_FRACTION`); above 1 the scan is an interior scan
    (:func:`scan_phantom`). ``dark_field_px`` > 0: the sample scatters at small angles and
    blurs the speckle behind its thickest part by a Gaussian of that sigma (detector pixels;
    :func:`dark_field_blur`). The diffuser is four layers of ``diffuser_grit`` sandpaper (the
    paper's P3000 by default), or grains of ``diffuser_radius_median_m``, of
    ``diffuser_grain_shape`` (:mod:`pwf_dask.physics.diffusers`). ``beads=False`` leaves the
    glass beads out: the cellulose cylinder alone, a sample of one material.
    ``detector_blur_fwhm_m`` and ``detector_halo`` = (fraction, 1/e radius in m): the detector's
    point-spread function, a Gaussian core and an exponential halo (:class:`SpeckleSetup`).
    ``optics`` replaces the paper's beamline (10 keV, 0.65 um pixels, L1 3 mm, L2 20 mm, coherence
    lengths 3.47 / 4.31 um) field by field: any of :data:`OPTICS_FIELDS`, in SI units. The
    phantom is drawn in metres from the frame's size, so a coarser pixel holds a larger sample.
    ``coherence_model="source"``: partial coherence from an extended source, which also moves the
    sample against the speckle (:attr:`SpeckleSetup.coherence_model`; default: the paper's IPSF).
    The phantom, the diffuser and the truth are recorded in the attributes.
    """
    from pwf_dask.stores import scan_io

    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    cfg = PRESETS[preset]
    # None takes the preset's value; a 0 given is checked, not replaced by the preset's
    shape = tuple(cfg["shape"] if shape is None else shape)
    n_ang = int(cfg["angles"] if angles is None else angles)
    n_pos = int(cfg["positions"] if positions is None else positions)
    photons = float(cfg["photons"] if photons is None else photons)
    _check_scene(shape, n_ang, n_pos, photons, diffuser_drift_px, cylinder_width_fraction, dark_field_px, zingers)
    _check_diffuser_and_axis(shape, rotation_axis_offset_px, diffuser_radius_median_m)
    optics = _checked_optics(optics, diffuser_upstream_m)
    setup = SpeckleSetup(
        shape=shape,
        photons=photons,
        diffuser_grit=diffuser_grit,
        diffuser_radius_median_m=diffuser_radius_median_m,
        diffuser_grain_shape=diffuser_grain_shape,
        detector_blur_fwhm_m=float(detector_blur_fwhm_m),
        detector_halo_fraction=float(detector_halo[0]),
        detector_halo_radius_m=float(detector_halo[1]),
        coherence_model=coherence_model,
        **optics,
    )
    if diffuser_upstream_m:
        setup = replace(setup, sample_diffuser_distance_m=0.0, diffuser_upstream_m=diffuser_upstream_m)
    setup.rotation_axis_offset_m = rotation_axis_offset_px * setup.pixel_size_m
    phantom = scan_phantom(shape, setup.pixel_size_m, seed, cylinder_width_fraction, cfg.get("bead_radius_m"))
    if not beads:
        phantom = replace(phantom, spheres=())
    angles_deg = np.linspace(0.0, 180.0, n_ang)
    attrs = {
        "energy_eV": setup.energy_eV,
        "pixel_size_m": setup.pixel_size_m,
        "sample_diffuser_distance_m": setup.sample_diffuser_distance_m,
        "diffuser_detector_distance_m": setup.diffuser_detector_distance_m,
        "flat_dark_corrected": not raw,
        **_simulation_attrs(setup, preset, seed, zingers, dark_field_px, diffuser_drift_px, phantom),
        "simulation_diffuser_grit": diffuser_grit if diffuser_radius_median_m is None else "",
    }
    g = scan_io.create_scan(
        path,
        n_positions=n_pos,
        angles_deg=angles_deg,
        shape=shape,
        pixel_size_m=setup.pixel_size_m,
        dtype="uint16" if raw else "float32",
        attrs=attrs,
        flat_dark=raw,
    )
    detector = SimulatedDetector(shape, photons, raw, seed, zingers)
    if raw:
        g["flat"][...], g["dark"][...] = detector.flat(), detector.dark()
        g.attrs["simulation_photons_per_count"] = detector.photons_per_count
    drift = np.asarray(diffuser_drift_px, float)
    _simulate_frames(g, setup, phantom, angles_deg, n_pos, seed, drift, dark_field_px, detector, progress)
    scan_io.consolidate(path)
    return str(path)


#: the beamline's fields of :class:`SpeckleSetup` that ``simulate_scan(optics=...)`` may replace
OPTICS_FIELDS = (
    "energy_eV",
    "pixel_size_m",
    "sample_diffuser_distance_m",
    "diffuser_detector_distance_m",
    "coherence_length_x_m",
    "coherence_length_y_m",
)


def _checked_optics(optics: dict | None, diffuser_upstream_m: float) -> dict:
    """``optics`` as floats, or one line naming the field that is unknown or out of range."""
    optics = {k: float(v) for k, v in (optics or {}).items()}
    unknown = sorted(set(optics) - set(OPTICS_FIELDS))
    if unknown:
        raise ValueError(
            f"simulate: unknown optics field(s) {', '.join(unknown)}; choose from {', '.join(OPTICS_FIELDS)}"
        )
    for name, value in optics.items():
        zero_allowed = name == "sample_diffuser_distance_m"
        if not (np.isfinite(value) and (value >= 0 if zero_allowed else value > 0)):
            raise ValueError(f"simulate: {name} must be finite and {'>= 0' if zero_allowed else '> 0'}, got {value}")
    if diffuser_upstream_m and optics.get("sample_diffuser_distance_m", 0.0) != 0.0:
        raise ValueError(
            "simulate: a diffuser upstream of the sample means L1 = 0; got sample_diffuser_distance_m "
            f"{optics['sample_diffuser_distance_m']} with diffuser_upstream_m {diffuser_upstream_m}"
        )
    return optics


def _check_diffuser_and_axis(shape, rotation_axis_offset_px: float, diffuser_radius_median_m) -> None:
    """One line for an axis that puts the sample outside the frame, or grains of no size."""
    if not abs(float(rotation_axis_offset_px)) < 0.5 * shape[1]:
        raise ValueError(
            f"simulate: rotation_axis_offset_px must lie inside the frame (|offset| < {0.5 * shape[1]:g} px "
            f"for {shape[1]} columns), got {rotation_axis_offset_px}"
        )
    if diffuser_radius_median_m is not None and not float(diffuser_radius_median_m) > 0:
        raise ValueError(f"simulate: diffuser_radius_median_m must be > 0, got {diffuser_radius_median_m}")


def _check_scene(shape, n_ang, n_pos, photons, drift_px, cylinder_width_fraction, dark_field_px, zingers) -> None:
    if n_ang < 2 or n_pos < 1 or min(shape) < 32 or not (photons > 0 and np.isfinite(photons)):
        raise ValueError(
            f"simulate: need >= 2 angles, >= 1 position, >= 32 x 32 px, finite photons > 0; got "
            f"{n_ang}, {n_pos}, {shape}, {photons}"
        )
    drift = np.asarray(drift_px, float)
    if drift.shape != (2,) or not np.all(np.isfinite(drift)):
        raise ValueError(f"simulate: diffuser_drift_px is a finite (dy, dx) pair, got {drift_px!r}")
    if cylinder_width_fraction is not None and not 0 < cylinder_width_fraction <= 10:
        raise ValueError(f"simulate: cylinder_width_fraction is in (0, 10], got {cylinder_width_fraction}")
    if not 0 <= dark_field_px <= 20:
        raise ValueError(f"simulate: dark_field_px is a blur sigma in [0, 20] px, got {dark_field_px}")
    if not 0 <= zingers < 0.1:
        raise ValueError(f"simulate: zingers is a fraction of the pixels in [0, 0.1), got {zingers}")


def _simulation_attrs(setup: SpeckleSetup, preset, seed, zingers, dark_field_px, drift_px, phantom) -> dict:
    """The truth a simulated scan records beside the contract's attributes (``simulation_*``;
    the grit, where one was named, is recorded by the caller)."""
    return {
        "simulated": True,
        "simulation_preset": preset,
        "simulation_photons": setup.photons,
        "simulation_seed": seed,
        "simulation_coherence_length_x_m": setup.coherence_length_x_m,
        "simulation_coherence_length_y_m": setup.coherence_length_y_m,
        "simulation_coherence_model": setup.coherence_model,
        "simulation_rotation_axis_offset_m": setup.rotation_axis_offset_m,
        "simulation_diffuser_upstream_m": setup.diffuser_upstream_m,
        "simulation_zingers": zingers,
        "simulation_dark_field_px": float(dark_field_px),
        "simulation_diffuser_radius_median_m": setup.diffuser_radius_median_m,
        "simulation_diffuser_grain_shape": setup.diffuser_grain_shape,
        "simulation_diffuser_drift_y_px": float(drift_px[0]),
        "simulation_diffuser_drift_x_px": float(drift_px[1]),
        "simulation_detector_blur_fwhm_m": setup.detector_blur_fwhm_m,
        "simulation_detector_halo_fraction": setup.detector_halo_fraction,
        "simulation_detector_halo_radius_m": setup.detector_halo_radius_m,
        "simulation_phantom": phantom_to_json(phantom),
    }


class SimulatedDetector:
    """Photon counting behind a beam profile: Poisson counts, zingers, and (``raw``) uint16 counts
    on a dark level, as a detector delivers them; else flat/dark-corrected float32 intensities."""

    #: the dark frame's counts
    DARK_LEVEL = 100.0
    #: the most counts a raw flat frame reaches: a quarter of the 16-bit range, as an exposure is
    #: set below full well, so that the speckle's bright spots (up to ~4x the flat) fit. Above
    #: it a count stands for several photons (:attr:`photons_per_count`, a camera's gain); below
    #: it one photon is one count. Without it 1e5 ph/px wrapped the flat past 65535 and clipped
    #: three quarters of every frame.
    FLAT_COUNTS_MAX = 16_000.0

    def __init__(self, shape: tuple[int, int], photons: float, raw: bool, seed: int, zingers: float):
        ny, nx = shape
        yy, xx = np.mgrid[0:ny, 0:nx]
        self.beam = 1.0 - 0.15 * (((xx - nx / 2) / nx) ** 2 + ((yy - ny / 2) / ny) ** 2)  # flat-field profile
        self.shape, self.photons, self.raw = shape, photons, raw
        self.photons_per_count = max(1.0, photons / self.FLAT_COUNTS_MAX) if raw else 1.0
        self.noise_rng = np.random.default_rng(seed + 7)
        # its own stream, so that a scan without zingers is the scan simulated before they existed
        self.zinger_rng = np.random.default_rng(seed + 13)
        self.n_zingers = int(round(zingers * ny * nx))

    def flat(self) -> np.ndarray:
        return np.round(self.beam * self.photons / self.photons_per_count + self.DARK_LEVEL).astype(np.uint16)

    def dark(self) -> np.ndarray:
        return np.full(self.shape, self.DARK_LEVEL, np.uint16)

    def _add_zingers(self, frame: np.ndarray, level: float) -> np.ndarray:
        hit = self.zinger_rng.choice(frame.size, self.n_zingers, replace=False)
        frame.flat[hit] += self.zinger_rng.uniform(2.0, 20.0, self.n_zingers) * level
        return frame

    def detect(self, intensity: np.ndarray) -> np.ndarray:
        """One frame of ``intensity`` (flat = 1) as the detector records it."""
        photons = self.photons
        if not self.raw:
            img = (self.noise_rng.poisson(np.clip(intensity, 0, None) * photons) / photons).astype(np.float32)
            return self._add_zingers(img, 1.0) if self.n_zingers else img
        detected = self.noise_rng.poisson(np.clip(intensity, 0, None) * self.beam * photons)
        counts = np.round(detected / self.photons_per_count) + self.DARK_LEVEL
        if self.n_zingers:
            counts = self._add_zingers(counts, photons / self.photons_per_count)
        return np.clip(counts, 0, 65535).astype(np.uint16)


def _simulate_frames(g, setup, phantom, angles_deg, n_pos, seed, drift, dark_field_px, detector, progress) -> None:
    """Every position's reference and projections into the store ``g``: one diffuser per
    position, moved by ``drift`` (px) linearly in time when it drifts."""
    n_ang = len(angles_deg)
    written = [0]
    with contextlib.ExitStack() as stack:
        if progress:
            stack.enter_context(Progress("simulate", n_pos * n_ang, lambda: written[0], unit="projections"))
        for k in range(n_pos):
            sim = SpeckleSimulator(setup, seed=seed + 101 * k)
            t = sim.diffuser()
            g["reference"][k] = detector.detect(sim.intensity(None, t))
            for a, ang in enumerate(angles_deg):
                fld, psi = sim.sample_field(phantom, float(ang))
                t_a = sim.diffuser(tuple(drift * a / (n_ang - 1))) if drift.any() else t
                dark_field = sim.dark_field_sigma_px(psi, dark_field_px)
                g["projections"][k, a] = detector.detect(sim.intensity(fld, t_a, dark_field))
                written[0] += 1
