"""The scan pipeline on Dask: retrieval per chain of angles, tomography per row block, FSC (docs/scan-format.md §2).

Every stage reads and writes the reconstruction store (:mod:`pwf_dask.stores.scan_io`) and is
resumable: retrieval recomputes only projections whose ``iterations`` is still -1 (written
last for each projection, after its phase and attenuation chunks); tomography recomputes
only row blocks whose ``tomo_done`` flag is 0. A killed run loses at most the projections
and row blocks in flight.
Dask appears here and in :mod:`pwf_dask.pipeline.cluster` only; the numerics stay pure functions.
"""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time
from functools import partial
from pathlib import Path

import numpy as np

from pwf_dask import __version__, calibration
from pwf_dask.backend import resolve_device, synchronize, task_stream, to_numpy
from pwf_dask.baselines.tracking import MIN_POSITIONS
from pwf_dask.calibration.diffuser import SAMPLE_FLOOR, check_nsr_floor
from pwf_dask.options import DEFAULTS, check_option_names
from pwf_dask.physics.detector import check_threshold, repair_outliers, saturated_pixels
from pwf_dask.physics.geometry import Geometry
from pwf_dask.physics.optics import check_detector_blur, wavelength_m
from pwf_dask.pipeline import estimate
from pwf_dask.pipeline.cluster import Runner, check_scheduler, worker_fft_threads
from pwf_dask.pwf.model import check_sample_field_grid
from pwf_dask.pwf.solver import (
    DEFAULT_ALPHA,
    NOISE_HIDDEN_SENSITIVITY,
    PAPER_ALPHA,
    TUNED_ATTENUATION_CONTRAST,
    rule_sensitivity,
    sensitivity_alpha,
)
from pwf_dask.retrieval import (
    DIFFUSER_FIELD_UPSAMPLE,
    METHODS,
    check_diffuser_drift,
    check_field_upsample,
    check_single_material,
    check_solver_options,
    parse_alpha,
)
from pwf_dask.stores import integrity, scan_io
from pwf_dask.tomo import fsc, tomography

log = logging.getLogger(__name__)

#: methods that combine the K diffuser positions of one angle into one projection
MULTI_IMAGE = ("lcs", "umpa", "mist")


def _read_corrected(g, name, index, flat, dark, corrected, with_saturated: bool = False):
    """One frame flat/dark-corrected; ``with_saturated``: and its saturated pixels
    (:func:`saturated_pixels`, at the scan's recorded full scale if it has one) beside it."""
    frame = integrity.read_checked(integrity.store_root(g), g[name], name, index)
    image = scan_io.correct(frame, flat, dark, corrected)
    if not with_saturated:
        return image
    return image, saturated_pixels(frame, corrected, g.attrs.get(scan_io.FULL_SCALE_ATTR))


#: scans whose saturated pixels this process has reported (one line each, not one per frame)
_SATURATION_REPORTED: set[str] = set()


def _report_saturation(scan_path, what: str, count: int) -> None:
    key = str(scan_path)
    if key not in _SATURATION_REPORTED:
        _SATURATION_REPORTED.add(key)
        log.warning(
            "%s: %d pixels of %s are saturated (raw counts at full scale); PWF leaves a sample frame's out of "
            "its fit, a reference's are read low: lower the exposure if many frames have them",
            key,
            count,
            what,
        )


def _read_reference(g, p, flat, dark, corrected, outlier_sigma):
    """Position p's corrected reference with its spikes repaired (:mod:`pwf_dask.physics.detector`):
    the coherence fit and the diffuser estimate read every pixel."""
    return repair_outliers(_read_corrected(g, "reference", p, flat, dark, corrected), outlier_sigma)[0]


def _scan_frames(scan_path):
    import zarr

    g = zarr.open_group(str(scan_path), mode="r")
    corrected = bool(g.attrs.get("flat_dark_corrected", False))
    flat, dark = (integrity.read_checked(str(scan_path), g[n], n) if n in g else None for n in ("flat", "dark"))
    return g, flat, dark, corrected


#: diffuser estimates held by this process, one per (scan, store, position, options): read
#: from the store once per worker, not once per task
_DIFFUSERS: dict = {}
_DIFFUSERS_LOCK = threading.Lock()
_DIFFUSER_OPTIONS = (
    "pad",
    "diffuser_model",
    "diffuser_material",
    "diffuser_beta_over_delta",
    "diffuser_refine_iter",
    "diffuser_nsr_floor",
    "phase_screen_iter",
    "diffuser_upstream_m",
    "detector_halo_fraction",
    "detector_halo_radius_m",
)
#: the reconstruction store's array of the fitted diffusers (position, y, x, re/im), float32
DIFFUSER_ARRAY = "diffuser"


def _absorption_model(attrs, options) -> str:
    """The diffuser model the options name, "auto" resolved by the grains' absorption alone
    (:func:`pwf_dask.retrieval.chosen_diffuser_model`)."""
    from pwf_dask import retrieval

    return retrieval.chosen_diffuser_model(
        options.get("diffuser_model", DEFAULTS.diffuser_model),
        options.get("diffuser_material", DEFAULTS.diffuser_material),
        options.get("diffuser_beta_over_delta"),
        float(attrs["energy_eV"]),
    )[0]


def _fit_diffuser(frames, p, reference, coherence, options, xp, fft_workers):
    """Position p's diffuser t_r fitted to its repaired reference (Methods, Diffuser
    transmission function; :func:`pwf_dask.retrieval.estimate_diffuser`), and its model: where
    ``"auto"`` probes (:func:`pwf_dask.retrieval.choose_diffuser`), on the position's projection
    at the middle angle, so that every task that fits it chooses alike.
    ``frames``: the scan as :func:`_scan_frames` opened it. Returns (t_r, model, each model's
    probe residual in % or {})."""
    from pwf_dask import retrieval

    g, flat, dark, corrected = frames
    model = _absorption_model(g.attrs, options)
    if retrieval.probes_diffuser(options.get("diffuser_model", DEFAULTS.diffuser_model), model):
        index = (p, g["projections"].shape[1] // 2)
        sample, clipped = _read_corrected(g, "projections", index, flat, dark, corrected, with_saturated=True)
        choice = retrieval.choose_diffuser(
            xp.asarray(sample),
            reference,
            **Geometry.from_attrs(g.attrs).keywords(with_upstream=False),
            coherence_length_x_m=coherence[0],
            coherence_length_y_m=coherence[1],
            bad_pixels=None if clipped is None else xp.asarray(clipped),
            **{**options, "fft_workers": fft_workers},
        )
        return choice.transmission, choice.model, choice.residuals_pct
    chosen = {k: options[k] for k in _DIFFUSER_OPTIONS if k in options}
    sigma = options.get("outlier_sigma", DEFAULTS.outlier_sigma)
    repaired, _ = repair_outliers(reference, sigma)
    sample = None
    if chosen.get("diffuser_nsr_floor", DEFAULTS.diffuser_nsr_floor) == SAMPLE_FLOOR:
        # the position's middle angle stands for its projections' noise, as the probe's does
        index = (p, g["projections"].shape[1] // 2)
        sample, _ = repair_outliers(xp.asarray(_read_corrected(g, "projections", index, flat, dark, corrected)), sigma)
    t = retrieval.estimate_diffuser(
        repaired,  # the fit reads every pixel
        sample=sample,
        energy_eV=float(g.attrs["energy_eV"]),
        pixel_size_m=float(g.attrs["pixel_size_m"]),
        diffuser_detector_distance_m=float(g.attrs["diffuser_detector_distance_m"]),
        coherence_length_x_m=coherence[0],
        coherence_length_y_m=coherence[1],
        fft_workers=fft_workers,
        **chosen,
    )
    return t, model, {}


def _diffuser_task(p, *, scan_path, options, device, fft_workers, coherence):
    """Stage task: position p's diffuser, fitted once for the whole scan; returned to the
    client (complex64) with its model, and stored for every projection task of the position."""
    frames = g, flat, dark, corrected = _scan_frames(scan_path)
    reference = _read_corrected(g, "reference", p, flat, dark, corrected)
    xp = resolve_device(device)
    t0 = time.perf_counter()
    t, model, probe = _fit_diffuser(
        frames, p, xp.asarray(reference), coherence[p], options, xp, worker_fft_threads(fft_workers)
    )
    return p, to_numpy(t).astype(np.complex64), time.perf_counter() - t0, model, probe


def _stored_diffuser(recon_path: str, p: int):
    """Position p's diffuser as stored by :func:`_fit_diffusers`, or None where it is not
    (a store made before, a damaged chunk: the caller fits it)."""
    import zarr

    if not Path(recon_path, DIFFUSER_ARRAY).exists():  # also before the store is made (alpha probe)
        return None
    g = zarr.open_group(recon_path, mode="r", use_consolidated=False)
    try:
        pair = integrity.read_checked(recon_path, g[DIFFUSER_ARRAY], DIFFUSER_ARRAY, p)
    except integrity.DamagedChunk:
        return None
    # positions' grids differ with their coherence (the padding): NaN beyond this one's
    valid = np.isfinite(pair[..., 0])
    ny, nx = int(valid.any(axis=1).sum()), int(valid.any(axis=0).sum())
    t = np.empty((ny, nx), dtype=np.complex64)
    t.real, t.imag = pair[:ny, :nx, 0], pair[:ny, :nx, 1]
    return t


def _diffuser_grid_shape(scan_path, coherence, options) -> tuple[int, int]:
    """The largest computational grid of the scan's positions (the stored array's)."""
    from pwf_dask.retrieval import diffuser_grid

    g = _scan_frames(scan_path)[0]
    kw = {k: options[k] for k in ("pad", "diffuser_upstream_m") if k in options}
    shapes = [
        diffuser_grid(
            g["reference"].shape[1:],
            energy_eV=float(g.attrs["energy_eV"]),
            pixel_size_m=float(g.attrs["pixel_size_m"]),
            diffuser_detector_distance_m=float(g.attrs["diffuser_detector_distance_m"]),
            coherence_length_x_m=cx,
            coherence_length_y_m=cy,
            **kw,
        )[1]
        for cx, cy in coherence
    ]
    return max(s[0] for s in shapes), max(s[1] for s in shapes)


def _fit_diffusers(runner, recon_path: str, positions: list[int], **task) -> dict:
    """Fit the diffusers of ``positions`` not yet in the store, one task per position, and
    store them (issue #31: once per position in a scan, whatever the number of workers).
    Returns {position: (seconds, model, probe residuals)} for :func:`_record_diffuser_models`."""
    import zarr

    todo = [p for p in positions if _stored_diffuser(recon_path, p) is None]
    if not todo:
        return {}
    fitted = runner.map(_diffuser_task, todo, label="diffuser", unit="positions", **task)
    g = zarr.open_group(recon_path, mode="r+", use_consolidated=False)
    shape = _diffuser_grid_shape(task["scan_path"], task["coherence"], task["options"])
    if DIFFUSER_ARRAY not in g or g[DIFFUSER_ARRAY].shape[1:3] != shape:
        n = g["phase"].shape[0]
        dims = ("position", "diffuser_y", "diffuser_x", "re_im")
        scan_io.create_variable(g, DIFFUSER_ARRAY, (n, *shape, 2), (1, *shape, 2), dims, "float32", np.nan)
    for p, t, *_ in fitted:
        pair = np.full((*shape, 2), np.nan, dtype=np.float32)
        pair[: t.shape[0], : t.shape[1], 0], pair[: t.shape[0], : t.shape[1], 1] = t.real, t.imag
        g[DIFFUSER_ARRAY][p] = pair
    return {p: (seconds, model, probe) for p, _, seconds, model, probe in fitted}


def _record_diffuser_models(g, fitted: dict) -> None:
    """The store's record of each position's diffuser fit: its seconds, its model
    (``diffuser_model_per_position``, which a resumed run reads back), the probe's residuals
    where ``"auto"`` probed, and ``diffuser_model_chosen``: the one model, or "per position"
    where they differ."""
    g.attrs["diffuser_fit_s"] = json.dumps({str(p): round(t, 3) for p, (t, _, _) in fitted.items()})
    models = json.loads(g.attrs.get("diffuser_model_per_position", "{}"))
    probes = json.loads(g.attrs.get("diffuser_probe_residual_pct", "{}"))
    for p, (_, model, probe) in fitted.items():
        models[str(p)] = model
        if probe:
            probes[str(p)] = {k: round(v, 4) for k, v in probe.items()}
    g.attrs["diffuser_model_per_position"] = json.dumps(models)
    if probes:
        g.attrs["diffuser_probe_residual_pct"] = json.dumps(probes)
    distinct = set(models.values())
    g.attrs["diffuser_model_chosen"] = distinct.pop() if len(distinct) == 1 else "per position"


def _stored_model(recon_path, p: int, attrs, options) -> str:
    """Position p's diffuser model as the store recorded it beside its diffuser, else (a store
    made before the record) the absorption rule's, which fitted it."""
    import zarr

    g = zarr.open_group(str(recon_path), mode="r", use_consolidated=False)
    models = json.loads(g.attrs.get("diffuser_model_per_position", "{}"))
    return models.get(str(p), _absorption_model(attrs, options))


def _position_diffuser(scan_path, recon_path, p, reference, frames, coherence, options, device, fft_workers):
    """Position p's diffuser and its model for a projection task: the stored fit (one read per
    worker), or a fit of this worker's own where the store has none."""
    chosen = {k: options[k] for k in _DIFFUSER_OPTIONS if k in options}
    repair = options.get("outlier_sigma", DEFAULTS.outlier_sigma)
    key = (str(scan_path), str(recon_path), p, tuple(coherence), device, repair, tuple(sorted(chosen.items())))
    with _DIFFUSERS_LOCK:  # threads of one worker wait for the one read or fit
        if key not in _DIFFUSERS:
            if len(_DIFFUSERS) >= 8:
                _DIFFUSERS.pop(next(iter(_DIFFUSERS)))
            stored = None if recon_path is None else _stored_diffuser(str(recon_path), p)
            if stored is None:
                xp = resolve_device(device)
                t, model, _ = _fit_diffuser(frames, p, reference, coherence, options, xp, fft_workers)
            else:
                t, model = (
                    resolve_device(device).asarray(stored),
                    _stored_model(recon_path, p, frames[0].attrs, options),
                )
            synchronize(resolve_device(device))  # other threads' streams will read t
            _DIFFUSERS[key] = (t, model)
        return _DIFFUSERS[key]


def _retrieve_task(item, *, scan_path, recon_path, options, device, fft_workers, coherence, start_from=None):
    """One projection: read, correct, retrieve, write its chunks, then its diagnostics.

    ``start_from`` (position, angle): PWF starts from that projection's stored result
    (:func:`angle_chains`); None: from zero, as the paper does.
    """
    t0 = time.perf_counter()
    # the task's device work on its thread's own stream; the host copies in _retrieved wait for it
    with task_stream(resolve_device(device)):
        res = _retrieve_item(item, scan_path, recon_path, options, device, fft_workers, coherence, start_from)
        return _retrieved(item, recon_path, t0, res)


def _retrieved(item, recon_path, t0: float, res):
    """Write one retrieved projection's chunks, then its diagnostics; the iterations last."""
    import zarr

    p, a = item
    out = zarr.open_group(str(recon_path), mode="r+", use_consolidated=False)
    out["phase"][p, a] = to_numpy(res.phase).astype(np.float32)
    out["attenuation"][p, a] = to_numpy(res.attenuation).astype(np.float32)
    out["converged"][p, a] = bool(res.converged)
    out["residual_rmse"][p, a] = np.float32(res.residual_rmse)
    if "outlier_pixels" in out:  # stores made before the detector test lack it
        out["outlier_pixels"][p, a] = np.int32(res.parameters.get("outlier_pixels", 0))
    if a == 0 and res.residual is not None and "preview_residual" in out:
        out["preview_residual"][p] = to_numpy(res.residual).astype(np.float32)
    planes = res.parameters.get("background_planes")
    if planes and "background_plane_phase" in out:  # stores made before warm starts kept them lack it
        out["background_plane_phase"][p, a] = np.asarray(planes["phase"], np.float64)
        out["background_plane_attenuation"][p, a] = np.asarray(planes["attenuation"], np.float64)
    if "diffuser_drift_px" in res.parameters and "diffuser_drift_y_px" in out:
        out["diffuser_drift_y_px"][p, a], out["diffuser_drift_x_px"][p, a] = res.parameters["diffuser_drift_px"]
    for name in ("speckle_shift_over_grain", "speckle_visibility", "sample_misfit"):
        if name in res.parameters and name in out:  # stores made before the check lack them
            out[name][p, a] = np.float32(res.parameters[name])
    seconds = time.perf_counter() - t0
    if "retrieval_seconds" in out:  # stores made before timings were kept lack it
        out["retrieval_seconds"][p, a] = np.float32(seconds)
    out["iterations"][p, a] = np.int32(res.iterations)  # last: marks the projection done
    return p, a, res.iterations, res.converged, res.residual_rmse, seconds, _peak_rss_mb()


def _start_psi(recon_path, item) -> np.ndarray:
    """PWF's psi of a stored projection, the start of the next in its chain: the stored phase
    and attenuation with the background planes they lost added back. Without them the start
    carries a tilt PWF's own solution did not have, and a tilt moves the whole speckle: on
    the full-width paper scan a projection restarted from its own stored result began at 13x
    its converged data misfit (22.5 against 1.73) and took 313 iterations; its neighbour
    from the solver's psi began at 3.8 (session 44). Stores without the planes start as before;
    with the single-material prior the stored phase's low frequencies are the prior's, so the
    start is PWF's psi only up to them."""
    import zarr

    from pwf_dask.physics.background import plane_from_terms

    done = zarr.open_group(str(recon_path), mode="r", use_consolidated=False)
    phase = done["phase"][item].astype(np.float64)
    attenuation = done["attenuation"][item].astype(np.float64)
    if "background_plane_phase" in done:
        planes = done["background_plane_phase"][item], done["background_plane_attenuation"][item]
        if np.all(np.isfinite(planes)):
            phase += plane_from_terms(planes[0], phase.shape)
            attenuation += plane_from_terms(planes[1], phase.shape)
    return (-attenuation + 1j * phase).astype(np.complex64)


def _retrieve_item(item, scan_path, recon_path, options, device, fft_workers, coherence, start_from=None):
    """Read and correct one projection and its reference, and retrieve it."""
    from pwf_dask.retrieval import retrieve_projection

    p, a = item
    g, flat, dark, corrected = _scan_frames(scan_path)
    if options.get("method") in MULTI_IMAGE:  # all K positions at this angle, one result
        npos = g["projections"].shape[0]
        sample = np.stack([_read_corrected(g, "projections", (k, a), flat, dark, corrected) for k in range(npos)])
        reference = np.stack([_read_corrected(g, "reference", k, flat, dark, corrected) for k in range(npos)])
        clipped = None  # the trackers fit every pixel
    else:
        sample, clipped = _read_corrected(g, "projections", (p, a), flat, dark, corrected, with_saturated=True)
        # as read: retrieve_projection repairs its spikes, and the diffuser fit (once per
        # position, :func:`_fit_diffusers`) repaired its own copy
        reference, clipped_reference = _read_corrected(g, "reference", p, flat, dark, corrected, with_saturated=True)
        if clipped_reference is not None:
            _report_saturation(scan_path, f"reference {p}", int(clipped_reference.sum()))
    xp = resolve_device(device)
    extra = {}
    if options.get("method", "pwf") == "pwf" and clipped is not None:
        extra["bad_pixels"] = xp.asarray(clipped)
        _report_saturation(scan_path, f"projection {(p, a)}", int(clipped.sum()))
    if start_from is not None:
        extra["initial"] = xp.asarray(_start_psi(recon_path, start_from))
    if options.get("method", "pwf") == "pwf":
        extra["diffuser"], extra["diffuser_model"] = _position_diffuser(
            scan_path,
            recon_path,
            p,
            xp.asarray(reference),
            (g, flat, dark, corrected),
            coherence[p],
            options,
            device,
            worker_fft_threads(fft_workers),
        )
    return retrieve_projection(
        xp.asarray(sample),
        xp.asarray(reference),
        **Geometry.from_attrs(g.attrs).keywords(with_upstream=False),  # options carry the upstream distance
        coherence_length_x_m=coherence[p][0],
        coherence_length_y_m=coherence[p][1],
        fft_workers=worker_fft_threads(fft_workers),
        **{**options, **extra},
    )


def choose_scan_alpha(scan_path, recon_path, options: dict, device: str, coherence) -> tuple[complex, str]:
    """alpha="discrepancy" for a scan: Im(alpha) by the discrepancy principle
    (:func:`pwf_dask.pwf.solver.discrepancy_alpha`) on one projection, position 0 at the middle
    angle, used for every projection. Returns (alpha, the rungs tried as JSON). A store that
    already chose keeps its choice, so a resumed run does not probe again."""
    import zarr

    if Path(recon_path).exists():
        try:
            attrs = zarr.open_group(str(recon_path), mode="r", use_consolidated=False).attrs
        except Exception:  # not a store: create_reconstruction says so in one line
            attrs = {}
        if attrs.get("alpha_rule") == "discrepancy":
            return complex(str(attrs["alpha"]).replace(" ", "")), str(attrs["alpha_trials"])
    n_angles = zarr.open_group(str(scan_path), mode="r", use_consolidated=False)["projections"].shape[1]
    item = (0, n_angles // 2)
    res = _retrieve_item(item, scan_path, recon_path, {**options, "alpha": "discrepancy"}, device, None, coherence)
    _say(f"alpha: {res.parameters['alpha']} by the discrepancy principle on projection {item}")
    return complex(res.parameters["alpha"]), json.dumps(res.parameters["alpha_trials"])


def guarded_scan_alpha(
    frames, recon_path, phase_s: float, options: dict, device: str, coherence, contrast: float = 0.0
):
    """alpha="sensitivity" for a scan (``frames`` as :func:`_scan_frames` opened it): the rule's
    alpha for the scan's phase sensitivity ``phase_s`` (as the rule takes it,
    :func:`pwf_dask.pwf.solver.rule_sensitivity`) and attenuation ``contrast``
    (:func:`pwf_dask.pwf.solver.sensitivity_alpha`, :func:`scan_attenuation_contrast`), one
    for every projection. Where the rule lowered it and the single-material diffuser fit misfits
    position 0's projection at the middle angle more than zero phase
    (:func:`pwf_dask.retrieval.alpha_rule_holds`, checked once as a projection checks it), what
    gives way is a projection's (:func:`pwf_dask.retrieval.alpha_rule_gives_up`): under
    ``"auto"`` the fit, for zero phase at the rule's alpha; a fit the user named keeps
    :data:`pwf_dask.pwf.solver.DEFAULT_ALPHA`.
    Returns (alpha, the probe's residual ratio or "n/a" where nothing was probed, "zero-phase"
    where ``"auto"`` gave up the fit, else None). A store that already probed keeps its ratio,
    so a resumed run does not probe again; one made by the rule before the probe (session 98),
    or that kept the default alpha under ``"auto"`` before it gave up the fit instead (session
    101), keeps its alpha, so that it resumes."""
    from pwf_dask import retrieval

    alpha = sensitivity_alpha(phase_s, attenuation_contrast=contrast)
    # where the fit gives way to the default Im(alpha), Re(alpha) stays the sample's
    default = complex(alpha.real, DEFAULT_ALPHA.imag)
    if not retrieval.guards_alpha_rule(phase_s, _absorption_model(frames[0].attrs, options)):
        return alpha, "n/a", None
    stored = _stored_alpha_rule(recon_path)
    if stored.get("alpha_rule") == "sensitivity" and "alpha_rule_model_ratio" not in stored:
        return complex(str(stored["alpha"]).replace(" ", "")), "n/a", None
    ratio = stored.get("alpha_rule_model_ratio")
    if not isinstance(ratio, float):
        ratio = retrieval.model_probe_ratio(_probed_models(frames, options, device, coherence[0]))
    if retrieval.alpha_rule_holds(ratio):
        return alpha, ratio, None
    if stored.get("alpha") == str(default).strip("()"):  # made before "auto" gave the fit up
        return default, ratio, None
    if retrieval.alpha_rule_gives_up(options.get("diffuser_model", DEFAULTS.diffuser_model)) == "model":
        return alpha, ratio, "zero-phase"
    return default, ratio, None


def _stored_alpha_rule(recon_path) -> dict:
    """The alpha rule's record (``alpha_rule``, ``alpha``, ``alpha_rule_model_ratio``) of an
    existing reconstruction store, {} where there is none."""
    import zarr

    if not Path(recon_path).exists():
        return {}
    try:
        attrs = zarr.open_group(str(recon_path), mode="r", use_consolidated=False).attrs
    except Exception:  # not a store: create_reconstruction says so in one line
        return {}
    return {k: attrs[k] for k in ("alpha_rule", "alpha", "alpha_rule_model_ratio") if k in attrs}


def _probed_models(frames, options: dict, device: str, coherence_xy) -> dict:
    """Each diffuser model's probe residual on position 0's projection at the middle angle
    (:func:`pwf_dask.retrieval.probe_diffuser_models`)."""
    from pwf_dask import retrieval

    g, flat, dark, corrected = frames
    index = (0, g["projections"].shape[1] // 2)
    sample, clipped = _read_corrected(g, "projections", index, flat, dark, corrected, with_saturated=True)
    reference = _read_corrected(g, "reference", 0, flat, dark, corrected)
    xp = resolve_device(device)
    return retrieval.probe_diffuser_models(
        xp.asarray(sample),
        xp.asarray(reference),
        Geometry.from_attrs(g.attrs),  # the options carry the upstream distance
        coherence_length_x_m=coherence_xy[0],
        coherence_length_y_m=coherence_xy[1],
        bad_pixels=None if clipped is None else xp.asarray(clipped),
        **options,
    )


def scan_phase_sensitivity(g, info, geometry: Geometry, flat, dark, corrected, outlier_sigma, measure=None) -> float:
    """The scan's phase sensitivity: :func:`pwf_dask.calibration.phase_sensitivity` averaged over
    the positions' references. Measured for every PWF scan: ``alpha="sensitivity"`` sets one
    alpha from it for every projection (a tomogram's slices must share their regularization,
    :func:`pwf_dask.pwf.solver.sensitivity_alpha`), and the scan's warning compares it with
    ``SensitivityLimits.min_phase_sensitivity``. ``measure``: another measure of a reference
    taken the same way (:func:`pwf_dask.calibration.phase_sensitivity_noise_bound`, where S
    reads none)."""
    wavelength = wavelength_m(geometry.energy_eV)
    measure = measure or calibration.phase_sensitivity
    values = [
        measure(
            _read_reference(g, p, flat, dark, corrected, outlier_sigma),
            wavelength,
            geometry.diffuser_detector_distance_m,
            geometry.pixel_size_m,
        )
        for p in range(info.n_positions)
    ]
    return float(np.mean(values))


#: the fractions of the angles at which :func:`scan_attenuation_contrast` reads position 0
CONTRAST_ANGLE_FRACTIONS = (0.0, 1 / 3, 2 / 3)


def scan_attenuation_contrast(g, flat, dark, corrected, outlier_sigma) -> float:
    """The scan's attenuation contrast (:func:`pwf_dask.calibration.attenuation_contrast`): the
    largest of position 0's projections at a third of the angles apart, against its reference.
    ``alpha="sensitivity"`` lowers one Re(alpha) for every projection from it (a tomogram's
    slices share their regularization), so the most absorbing of the three views sets it."""
    reference = _read_reference(g, 0, flat, dark, corrected, outlier_sigma)
    n = g["projections"].shape[1]
    values = []
    for index in sorted({int(f * n) for f in CONTRAST_ANGLE_FRACTIONS}):
        sample = _read_corrected(g, "projections", (0, index), flat, dark, corrected)
        values.append(calibration.attenuation_contrast(repair_outliers(sample, outlier_sigma)[0], reference))
    return float(max(values))


def _peak_rss_mb() -> float:
    """Peak resident memory of this process (MB): the worker's, on distributed."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


#: projections per warm-start chain of the retrieval stage (``angle_chain``; docs/user-guide.md, Warm
#: starts along the angles)
DEFAULT_ANGLE_CHAIN = 8


def angle_chains(angles_deg, n_positions: int, chain_length: int) -> list[list[tuple[int, int]]]:
    """The retrieval stage's tasks: chains of (position, angle index), each in angle order.

    Within a chain every projection after the first starts PWF from the one before (its
    stored phase and attenuation), two angular steps away: the even and odd angles (in angle
    order) and the diffuser positions stay in separate chains, so the halves and positions
    that the FSC compares never share a start. The first projection of a chain starts from
    zero; ``chain_length`` 1 is every projection from zero, the paper's procedure.
    """
    if int(chain_length) < 1:
        raise ValueError(f"angle_chain is a number of projections >= 1, got {chain_length}")
    order = np.argsort(np.asarray(angles_deg), kind="stable")
    chains = []
    for p in range(n_positions):
        for half in (order[0::2], order[1::2]):
            for s in range(0, len(half), int(chain_length)):
                chains.append([(p, int(a)) for a in half[s : s + int(chain_length)]])
    return chains


def _retrieve_chain(chain, **task):
    """The projections of one chain still missing, in order, each started from the stored
    result of the one before it in the chain: a resumed chain starts where a killed one
    stopped, from the same values."""
    import zarr

    done = zarr.open_group(task["recon_path"], mode="r", use_consolidated=False)["iterations"]
    results = []
    for i, item in enumerate(chain):
        if int(done[item]) < 0:
            results.append(_retrieve_task(item, start_from=chain[i - 1] if i else None, **task))
    return results


def retrieve_scan(
    scan_path,
    recon_path,
    *,
    scheduler: str = "threads",
    device: str = "cpu",
    method: str = DEFAULTS.method,
    max_iter: int = DEFAULTS.max_iter,
    tol: float = DEFAULTS.tol,
    gamma: float = DEFAULTS.gamma,
    alpha=DEFAULTS.alpha,
    step: float = DEFAULTS.step,
    precision: str = DEFAULTS.precision,
    outlier_sigma: float | None = DEFAULTS.outlier_sigma,
    angle_chain: int = DEFAULT_ANGLE_CHAIN,
    runner: Runner | None = None,
    **options,
) -> dict:
    """Retrieval stage: every missing (position, angle) projection, one task per chain of
    ``angle_chain`` projections (PWF; :func:`angle_chains`), one per projection otherwise.

    ``options`` are further options of :func:`retrieve_projection`
    (:class:`pwf_dask.options.RetrievalOptions`). ``outlier_sigma`` is the detector-defect
    threshold of :func:`retrieve_projection`; the references are repaired with it before the
    coherence fit and the diffuser estimate.
    """
    angle_chain, alpha_c = _checked_scan_options(
        method, scheduler, device, max_iter, tol, gamma, alpha, step, outlier_sigma, angle_chain, options
    )
    # tasks may run in other working directories (distributed workers)
    scan_path, recon_path = str(Path(scan_path).resolve()), str(Path(recon_path).resolve())
    if Path(recon_path).is_relative_to(scan_path) or Path(scan_path).is_relative_to(recon_path):
        raise ValueError(f"{recon_path}: the reconstruction store must lie outside the scan store {scan_path}")
    ds, info = scan_io.open_scan(scan_path)
    # the scan's recorded geometry unless the caller gave the upstream distance (PWF reads it)
    geometry = Geometry.from_attrs(
        info.attrs, options.get("diffuser_upstream_m", info.diffuser_upstream_m) if method == "pwf" else 0.0
    )
    if method == "pwf":
        options["diffuser_upstream_m"] = geometry.diffuser_upstream_m
    if info.n_positions < MIN_POSITIONS.get(method, 1):
        raise ValueError(
            f"method {method} needs K >= {MIN_POSITIONS[method]} diffuser positions; the scan has {info.n_positions}"
        )
    g, flat, dark, corrected = _scan_frames(scan_path)
    coherence, fits = [(float("nan"), float("nan"))] * info.n_positions, []  # the trackers use no coherence model
    if method == "pwf":
        coherence, fits = _position_coherence(g, info, geometry, flat, dark, corrected, outlier_sigma, options)
    if fits:
        # the tasks are given the lengths: they must know whether the pixel's blur is in them
        options["coherence_includes_pixel_blur"] = fits[0][0].includes_pixel_blur
    alpha_rule, alpha_trials, phase_s, model_ratio, instead = "given", "n/a", "n/a", "n/a", None
    contrast, noise_bound = "n/a", "n/a"
    if method == "pwf":
        phase_s = scan_phase_sensitivity(g, info, geometry, flat, dark, corrected, outlier_sigma)
    if method == "pwf" and alpha_c == "sensitivity" and phase_s <= 0:  # does the noise hide it?
        bound_of = calibration.phase_sensitivity_noise_bound
        noise_bound = scan_phase_sensitivity(g, info, geometry, flat, dark, corrected, outlier_sigma, bound_of)
    if alpha_c == "discrepancy" and method == "pwf":
        probe = dict(method=method, max_iter=max_iter, tol=tol, gamma=gamma, step=step, precision=precision)
        probe.update(outlier_sigma=outlier_sigma, **options)
        alpha_c, alpha_trials = choose_scan_alpha(scan_path, recon_path, probe, device, coherence)
        alpha_rule = "discrepancy"
    elif alpha_c == "sensitivity" and method == "pwf":
        probe = dict(precision=precision, outlier_sigma=outlier_sigma, **options)
        frames = (g, flat, dark, corrected)  # as opened above: flat and dark read once
        contrast = scan_attenuation_contrast(g, flat, dark, corrected, outlier_sigma)
        rule_s = rule_sensitivity(phase_s, noise_bound if isinstance(noise_bound, float) else None)
        alpha_c, model_ratio, instead = guarded_scan_alpha(
            frames, recon_path, rule_s, probe, device, coherence, contrast
        )
        alpha_rule = "sensitivity"
    elif alpha_c in ("discrepancy", "sensitivity"):  # the speckle-tracking baselines have no alpha
        alpha_c, alpha_rule = PAPER_ALPHA, "n/a"
    if method in MULTI_IMAGE:
        from dataclasses import replace

        info = replace(info, n_positions=1)  # one reconstruction from all K positions
    params = {
        "method": method,
        "gamma": float(gamma),
        "alpha": str(alpha_c).strip("()"),
        "alpha_rule": alpha_rule,
        "alpha_trials": alpha_trials,
        "phase_sensitivity": phase_s,
        "phase_sensitivity_noise_bound": noise_bound,
        "attenuation_contrast": contrast,
        "alpha_rule_model_ratio": model_ratio,
        "step": float(step),
        "tol": float(tol),
        "max_iter": int(max_iter),
        "precision": precision,
        "outlier_sigma": float(outlier_sigma or 0),
        "device": device,
        **_coherence_record(method, coherence, fits, info),
        "pwf_dask_version": __version__,
        "scan_fingerprint": integrity.scan_fingerprint(g).encode(),
        "angle_chain": angle_chain,
        **_model_record(method, options, info.energy_eV),
    }
    opts = dict(method=method, max_iter=max_iter, tol=tol, gamma=gamma, alpha=alpha_c, step=step)
    opts.update(precision=precision, outlier_sigma=outlier_sigma, **options)
    if instead:  # "auto" gave up the single-material fit for the alpha rule (guarded_scan_alpha)
        params["diffuser_model_chosen"] = opts["diffuser_model"] = instead
    own = runner is None
    runner = runner or Runner(scheduler)  # a bad scheduler fails here, before anything is written
    threads = runner.workers
    try:
        runner.workers = _gpu_threads(runner, device, info, opts)
        return _run_retrieval(runner, info, params, scan_path, recon_path, opts, device, coherence, angle_chain)
    finally:
        runner.workers = threads
        if own:
            runner.close()


def _device_free_bytes(xp) -> int:
    """Free memory of the current GPU, CuPy's pool not counted as used."""
    return int(xp.cuda.Device().mem_info[0]) + int(xp.get_default_memory_pool().free_bytes())


def _gpu_threads(runner: Runner, device: str, info, opts: dict) -> int | None:
    """The threads that share this host's GPU (``--device gpu`` on a local scheduler): as many
    as the scheduler runs, but no more than fit in the GPU's free memory
    (:func:`estimate.gpu_tasks_that_fit`); a cluster's workers (dask-cuda) hold one GPU each."""
    xp = resolve_device(device)
    if xp is np or runner.client is not None:
        return runner.workers
    field = opts.get("field_upsample", "auto")
    field = DIFFUSER_FIELD_UPSAMPLE if field == "auto" else float(field)
    task_mb = estimate.retrieval_device_mb(info.shape, field, positions=info.n_positions)
    free = _device_free_bytes(xp)
    fit = estimate.gpu_tasks_that_fit(task_mb, free)
    if fit >= runner.concurrency:
        return runner.workers
    _say(f"retrieve: {fit} projections at a time on the GPU ({task_mb:.0f} MB each, {free / 1e9:.1f} GB free)")
    return fit


def _checked_scan_options(
    method, scheduler, device, max_iter, tol, gamma, alpha, step, outlier_sigma, angle_chain, options: dict
):
    """The retrieval stage's options checked before anything is read or written, each refused
    in one line naming it: returns the chain length used and alpha parsed; a given field grid
    is replaced in ``options`` by its checked value."""
    check_option_names(options)  # a misspelt option fails here, not in every task
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}: choose one of {', '.join(METHODS)}")
    check_scheduler(scheduler)
    if "://" not in scheduler:  # tasks run on this host: fail early on --device gpu without CuPy
        resolve_device(device)
    check_threshold(outlier_sigma)
    check_diffuser_drift(options.get("diffuser_drift", DEFAULTS.diffuser_drift))
    check_single_material(options.get("single_material", DEFAULTS.single_material), method)
    angle_chains((), 1, angle_chain)  # a bad length fails here, before anything is written
    # only PWF iterates from a start, and a start the user chose is kept for every projection
    angle_chain = int(angle_chain) if method == "pwf" and "initial" not in options else 1
    alpha_c = parse_alpha(alpha)
    check_solver_options(
        max_iter,
        tol,
        gamma,
        step,
        options.get("phase_scale", DEFAULTS.phase_scale),
        options.get("stationary_terms", DEFAULTS.stationary_terms),
        options.get("low_band_atol_rad", DEFAULTS.low_band_atol_rad),
    )
    if "field_upsample" in options:
        options["field_upsample"] = check_field_upsample(options["field_upsample"])
    check_sample_field_grid(options.get("sample_field_grid", DEFAULTS.sample_field_grid))
    check_detector_blur(
        0.0,
        options.get("detector_halo_fraction", DEFAULTS.detector_halo_fraction),
        options.get("detector_halo_radius_m", DEFAULTS.detector_halo_radius_m),
    )
    check_nsr_floor(options.get("diffuser_nsr_floor", DEFAULTS.diffuser_nsr_floor))
    return angle_chain, alpha_c


def _position_coherence(g, info, geometry: Geometry, flat, dark, corrected, outlier_sigma, options: dict):
    """Each diffuser position's coherence lengths (x, y): the scan's, or calibrated on the
    position's repaired reference (Methods, IOTF); and the fits made, each with its seconds."""
    coherence, fits = [], []
    for p in range(info.n_positions):
        cx, cy = info.coherence_length_x_m, info.coherence_length_y_m
        if cx is None or cy is None:
            ref = _read_reference(g, p, flat, dark, corrected, outlier_sigma)
            started = time.perf_counter()
            fit = calibration.fit_coherence_lengths(
                ref,
                geometry.pixel_size_m,
                energy_eV=geometry.energy_eV,
                diffuser_detector_distance_m=geometry.speckle_distance_m,
                diffuser_material=options.get("diffuser_material", DEFAULTS.diffuser_material),
                method=options.get("coherence_method", DEFAULTS.coherence_method),
            )
            fits.append((fit, time.perf_counter() - started))
            cx = fit.x_m if cx is None else cx
            cy = fit.y_m if cy is None else cy
        coherence.append((float(cx), float(cy)))
    return coherence, fits


def _coherence_record(method: str, coherence, fits, info) -> dict:
    """The coherence lengths a store was retrieved with and how each was found ("n/a": the
    speckle-tracking baselines use no coherence model)."""
    if method != "pwf":
        return {
            "coherence_length_x_m": "n/a",
            "coherence_length_y_m": "n/a",
            "coherence_lengths_per_position_m": "n/a",
            "coherence_calibrated": info.coherence_length_x_m is None or info.coherence_length_y_m is None,
            "coherence_fits_per_position": "n/a",
        }
    return {
        "coherence_length_x_m": float(np.mean([c[0] for c in coherence])),
        "coherence_length_y_m": float(np.mean([c[1] for c in coherence])),
        "coherence_lengths_per_position_m": json.dumps(coherence),
        "coherence_calibrated": info.coherence_length_x_m is None or info.coherence_length_y_m is None,
        "coherence_fits_per_position": json.dumps(
            [
                {
                    "method": f.method,
                    "template": f.template,
                    "grain_radius_m": f.grain_radius_m,
                    "reference_photons_per_px": f.reference_photons_per_px,
                    "seconds": round(t, 3),
                }
                for f, t in fits
            ]
        )
        if fits
        else "n/a",
    }


def _model_record(method: str, options: dict, energy_eV: float) -> dict:
    """The diffuser model, the single-material prior, the further options given (numbers,
    strings, flags) and the one sample material assumed (MIST, the prior), as used."""
    record = {
        "diffuser_model": options.get("diffuser_model", DEFAULTS.diffuser_model) if method == "pwf" else "n/a",
        "single_material": bool(options.get("single_material", DEFAULTS.single_material)) if method == "pwf" else "n/a",
        **{
            k: v
            for k, v in options.items()
            if isinstance(v, (int, float, str, bool)) and (method == "mist" or not k.startswith("sample_"))
        },
    }
    if method == "pwf":  # what "auto" chose at this energy (the same for every position)
        from pwf_dask.retrieval import chosen_diffuser_model

        record["diffuser_model_chosen"] = chosen_diffuser_model(
            record["diffuser_model"],
            options.get("diffuser_material", DEFAULTS.diffuser_material),
            options.get("diffuser_beta_over_delta"),
            energy_eV,
        )[0]
    if method == "mist" or options.get("single_material"):
        from pwf_dask.retrieval import sample_delta_over_beta_of

        material = options.get("sample_material", DEFAULTS.sample_material)
        record["sample_material"] = material
        record["sample_delta_over_beta"] = sample_delta_over_beta_of(
            material, options.get("sample_delta_over_beta"), energy_eV
        )
    return record


def _alpha_rule_line(params: dict) -> str:
    """What ``alpha="sensitivity"`` chose for the scan, in one line."""
    line = f"alpha: {params['alpha']} for the data's phase sensitivity {params['phase_sensitivity']:.3g}"
    bound = params.get("phase_sensitivity_noise_bound", "n/a")
    if isinstance(bound, float) and bound >= NOISE_HIDDEN_SENSITIVITY:
        line += f" (none above the photon noise, which could hide {bound:.3g}: that taken)"
    contrast = params.get("attenuation_contrast", "n/a")
    if isinstance(contrast, float) and contrast > TUNED_ATTENUATION_CONTRAST:
        line += f" and the sample's attenuation contrast {contrast:.3g} (Re(alpha) lowered)"
    ratio = params.get("alpha_rule_model_ratio", "n/a")
    if ratio == "n/a":
        return line
    from pwf_dask.retrieval import alpha_rule_holds

    if alpha_rule_holds(ratio):
        return f"{line} (the single-material diffuser fit's probe residual {ratio:.3g}x zero phase's)"
    if params.get("diffuser_model_chosen") == "zero-phase":
        return f"{line}, with the zero-phase diffuser: the single-material fit misfits the sample {ratio:.3g}x as much"
    return (
        f"{line}: the default, not lowered, as the single-material diffuser fit misfits the sample"
        f" {ratio:.3g}x as much as zero phase"
    )


def _run_retrieval(runner, info, params, scan_path, recon_path, opts, device, coherence, angle_chain) -> dict:
    """Create or reopen the store, verify what it holds, and compute the missing projections."""
    import zarr

    created = not Path(recon_path).exists()
    grp = scan_io.create_reconstruction(recon_path, info, params)
    done = _verified_done(runner, recon_path, grp)
    chains = [c for c in angle_chains(grp["angle"][...], done.shape[0], angle_chain) if any(done[i] < 0 for i in c)]
    missing = int((done < 0).sum())
    if params["alpha_rule"] == "sensitivity":  # said once the store is known to be this scan's
        _say(_alpha_rule_line(params))
    _say(f"retrieve: {missing} of {done.size} projections to compute ({done.size - missing} already done)")
    t0 = time.perf_counter()
    try:
        if opts.get("method", "pwf") == "pwf":
            positions = sorted({p for chain in chains for p, _ in chain})
            fitted = _fit_diffusers(
                runner,
                recon_path,
                positions,
                scan_path=scan_path,
                options=opts,
                device=device,
                fft_workers=runner.fft_workers(),
                coherence=coherence,
            )
            if fitted:
                _record_diffuser_models(grp, fitted)
        chained = runner.map(
            _retrieve_chain,
            chains,
            label="retrieve",
            unit="projections",
            count=partial(_count_done, recon_path, "iterations", 0),
            total=done.size,
            scan_path=scan_path,
            recon_path=recon_path,
            options=opts,
            device=device,
            fft_workers=runner.fft_workers(),
            coherence=coherence,
        )
    except Exception:
        if created and _count_done(recon_path, "iterations", 0) == 0:
            # a store this call made and nothing saved in it would only block the corrected re-run
            shutil.rmtree(recon_path, ignore_errors=True)
        raise
    results = [r for chain in chained for r in chain]
    wall = time.perf_counter() - t0
    grp = zarr.open_group(recon_path, mode="r+", use_consolidated=False)
    if results:
        a = grp.attrs
        a["retrieval_wall_s"] = wall
        a["retrieval_task_s_mean"] = float(np.mean([r[5] for r in results]))
        # of any one worker process, over every run that filled the store
        a["retrieval_peak_rss_mb"] = float(max([r[6] for r in results] + [a.get("retrieval_peak_rss_mb", 0.0)]))
        # a store filled over several (resumed) runs: the totals of all of them
        a["retrieval_wall_s_total"] = float(a.get("retrieval_wall_s_total", 0.0)) + wall
        a["retrieval_task_s_total"] = float(a.get("retrieval_task_s_total", 0.0)) + float(sum(r[5] for r in results))
        a["retrieval_tasks_timed"] = int(a.get("retrieval_tasks_timed", 0)) + len(results)
    if opts["method"] == "pwf" and info.n_positions >= 2 and (results or POSITION_DISAGREEMENT not in grp):
        _record_position_disagreement(runner, recon_path, grp)
    _warn_sensitivity(grp)
    scan_io.consolidate(recon_path)
    return {"computed": len(results), "wall_s": wall, "coherence": coherence, "tasks": results}


#: the store's variable of :func:`pwf_dask.calibration.position_disagreement`, (position, angle)
POSITION_DISAGREEMENT = "position_disagreement"


def _disagreement_task(angles: list[int], *, recon_path: str) -> list[list[float]]:
    """:func:`pwf_dask.calibration.position_disagreement` of each angle whose every position is
    retrieved; NaN for each position of an angle that is not."""
    import zarr

    from pwf_dask.calibration import position_disagreement

    g = zarr.open_group(recon_path, mode="r", use_consolidated=False)
    done = g["iterations"][...]
    nan = [float("nan")] * done.shape[0]
    return [position_disagreement(g["phase"][:, a]) if (done[:, a] >= 0).all() else nan for a in angles]


def _record_position_disagreement(runner, recon_path: str, grp) -> None:
    """A scan of K >= 2 diffuser positions retrieves every projection K times from independent
    speckle: their disagreement per (position, angle), in batches of 16 angles on the scheduler
    (one read of the phases), stored whole (docs/validation.md, 'What the data carry')."""
    npos, nang = grp["iterations"].shape
    batches = [list(range(i, min(i + 16, nang))) for i in range(0, nang, 16)]
    found = runner.map(_disagreement_task, batches, label="agreement", unit="angle batches", recon_path=recon_path)
    values = np.asarray([v for batch in found for v in batch], dtype=np.float32).T
    dims = ("position", "angle")
    scan_io.create_variable(grp, POSITION_DISAGREEMENT, (npos, nang), (npos, nang), dims, "float32", np.nan, values)


def sensitivity_warning(
    shift_over_grain: np.ndarray,
    visibility: np.ndarray,
    misfit: np.ndarray | None = None,
    disagreement: np.ndarray | None = None,
    phase_sensitivity: float | None = None,
    misfit_hint: str = "",
) -> str | None:
    """One line where some projections lie beyond :class:`pwf_dask.calibration.SensitivityLimits`
    (the data carry little of their phase, the model does not fit the sample, or the diffuser
    positions disagree), or the scan's ``phase_sensitivity`` (:func:`scan_phase_sensitivity`)
    lies below its limit, else None; NaN or None (not measured) counts as neither.
    ``misfit_hint`` (:func:`~pwf_dask.calibration.sensitivity.misfit_hint`) follows a misfit's words."""
    from pwf_dask.calibration import SensitivityLimits
    from pwf_dask.calibration.sensitivity import insensitive_words

    limits = SensitivityLimits()
    measured = np.isfinite(shift_over_grain)
    small = measured & (shift_over_grain < limits.min_shift_over_grain)
    faint = measured & (visibility < limits.min_visibility)
    insensitive = phase_sensitivity is not None and phase_sensitivity < limits.min_phase_sensitivity
    lines = []
    if (small | faint).any() or insensitive:
        parts = []
        if insensitive:
            parts.append(insensitive_words(phase_sensitivity, limits))
        if small.any():
            median = float(np.median(shift_over_grain[measured]))
            parts.append(
                f"the sample moves the speckle by under {limits.min_shift_over_grain:g} of its grain on "
                f"{int(small.sum())} of {int(measured.sum())} projections (median {median:.3f})"
            )
        if faint.any():
            parts.append(
                f"the reference's speckle visibility is under {limits.min_visibility:g} on {int(faint.sum())} "
                f"(median {np.median(visibility[measured]):.3f})"
            )
        lines.append(
            "; ".join(parts) + ": the data carry little of the phase there, and the phase returned is "
            "unreliable, mostly too low (docs/validation.md, 'What the data carry')"
        )
    if misfit is not None:
        lines.append(_unfit_line(np.asarray(misfit), limits.max_sample_misfit, misfit_hint))
    if disagreement is not None:
        lines.append(_disagreement_line(np.asarray(disagreement), limits.max_position_disagreement))
    return "; ".join(line for line in lines if line) or None


def _disagreement_line(disagreement: np.ndarray, limit: float) -> str | None:
    """The summary's words for the angles whose diffuser positions disagree by over ``limit``
    (:func:`pwf_dask.calibration.position_disagreement`; every position of an angle reads alike
    for K = 2, so an angle counts once, by its largest)."""
    per_angle = np.max(np.where(np.isfinite(disagreement), disagreement, -np.inf), axis=0)
    measured = np.isfinite(per_angle)
    apart = measured & (per_angle > limit)
    if not apart.any():
        return None
    return (
        f"the diffuser positions' phases disagree by over {limit:g} of their rms on {int(apart.sum())} of "
        f"{int(measured.sum())} angles (median {float(np.median(per_angle[measured])):.2f}): a position's phase is "
        "unreliable there, and their mean too (docs/validation.md, 'What the data carry')"
    )


def _unfit_line(misfit: np.ndarray, limit: float, hint: str = "") -> str | None:
    """The summary's words for the projections whose fit leaves over ``limit`` times the
    background's misfit in the sample (:func:`pwf_dask.calibration.sensitivity.sample_misfit`),
    and ``hint`` after them (:func:`~pwf_dask.calibration.sensitivity.misfit_hint`)."""
    measured = np.isfinite(misfit)
    unfit = measured & (misfit > limit)
    if not unfit.any():
        return None
    return (
        f"the fit leaves over {limit:g} times the background's misfit inside the sample on "
        f"{int(unfit.sum())} of {int(measured.sum())} projections (the largest {float(misfit[unfit].max()):.2f}): "
        "the model does not reach the sample's data there, and the phase returned is unreliable "
        "(docs/validation.md, 'What the data carry')" + hint
    )


def _warn_sensitivity(grp) -> None:
    """Log :func:`sensitivity_warning` of the store's projections (all of them, resumed runs too)."""
    from pwf_dask.calibration.sensitivity import misfit_hint

    if "speckle_shift_over_grain" not in grp:
        return
    misfit = grp["sample_misfit"][...] if "sample_misfit" in grp else None  # stores made before session 84 lack it
    apart = grp[POSITION_DISAGREEMENT][...] if POSITION_DISAGREEMENT in grp else None  # K >= 2 only
    s = grp.attrs.get("phase_sensitivity")  # "n/a" for the trackers and in stores made before session 92
    a = grp.attrs
    hint = misfit_hint(a.get("sample_diffuser_distance_m"), a.get("diffuser_upstream_m", 0.0))
    line = sensitivity_warning(
        grp["speckle_shift_over_grain"][...],
        grp["speckle_visibility"][...],
        misfit,
        apart,
        s if isinstance(s, (int, float)) else None,
        misfit_hint=hint,
    )
    if line:
        log.warning(f"retrieve: warning: {line}")


def _say(message: str) -> None:
    log.info(message)


def _report_damage(stage: str, damaged: list, what: str) -> None:
    """One line per damaged chunk (ten at most): a repair is never silent."""
    for d in damaged[:10]:
        _say(f"{stage}: {d}: {what}")
    if len(damaged) > 10:
        _say(f"{stage}: ... and {len(damaged) - 10} more damaged chunks: {what}")


def _verified_done(runner, recon_path: str, grp) -> np.ndarray:
    """``iterations`` as trusted: a projection marked done counts only if its chunks are all
    there and decode (checksums; :mod:`pwf_dask.stores.integrity`); any other is named, marked not
    done and recomputed. The decode pass reads what is stored once (on a resume)."""
    done, damaged = integrity.read_bookkeeping(recon_path, grp, "iterations")
    _report_damage("retrieve", damaged, "its projection is recomputed")
    for (p, a), lost in integrity.missing_projection_chunks(recon_path, grp, done).items():
        name, index = lost[0]
        _say(f"retrieve: {recon_path}: {name} chunk {index} of projection ({p}, {a}) is missing: recomputed")
        integrity.reset_projection(recon_path, grp, p, a)
        done[p, a] = -1
    stored = [integrity.projection_chunks(grp, int(p), int(a)) for p, a in zip(*np.nonzero(done >= 0))]
    for fault in _decode_all(runner, recon_path, "projection", stored):
        p, a = fault.index[:2]
        _say(f"retrieve: {fault} (projection ({p}, {a})): recomputed")
        integrity.reset_projection(recon_path, grp, p, a)
        done[p, a] = -1
    return done


def _decode_task(chunk_lists, *, recon_path):
    """The first fault of each list of (array, chunk index), if any."""
    import zarr

    g = zarr.open_group(recon_path, mode="r", use_consolidated=False)
    faults = []
    for chunks in chunk_lists:
        for name, index in chunks:
            try:
                integrity.read_chunk(recon_path, g[name], name, index)
            except integrity.DamagedChunk as exc:
                faults.append(exc)
                break
    return faults


def _decode_all(runner, recon_path: str, what: str, chunk_lists: list) -> list:
    """Decode every chunk of ``chunk_lists`` (one list per projection or row block) on the
    scheduler, in batches of 16 lists; the first fault of each list that has one."""
    if not chunk_lists:
        return []
    batches = [chunk_lists[i : i + 16] for i in range(0, len(chunk_lists), 16)]
    found = runner.map(_decode_task, batches, label="verify", unit=f"{what} batches", recon_path=recon_path)
    return [f for batch in found for f in batch]


def _count_done(recon_path: str, name: str, done_from: int) -> int:
    """Entries of the store's bookkeeping array ``name`` at or above ``done_from`` (progress)."""
    import zarr

    group = zarr.open_group(recon_path, mode="r", use_consolidated=False)
    return int((group[name][...] >= done_from).sum())


# --- tomography -------------------------------------------------------------------------


def _read_sinogram(g, recon_path, name, p, rows, b) -> tuple[np.ndarray | None, list]:
    """Row block ``b`` of position p's sinogram; or None and the damaged chunks (named, removed,
    their projections marked not done): a chunk is never read as its fill value or garbage."""
    arr = g[name]
    idx = [(p, a, b, 0) for a in range(arr.shape[1])]
    damaged = [
        integrity.DamagedChunk(recon_path, name, i, "missing")
        for i in idx
        if not integrity.chunk_path(recon_path, name, i).exists()
    ]
    if not damaged:
        try:
            return arr[p, :, rows, :], []
        except Exception:
            for i in idx:
                try:
                    integrity.read_chunk(recon_path, arr, name, i)
                except integrity.DamagedChunk as exc:
                    damaged.append(exc)
    for d in damaged:
        integrity.reset_projection(recon_path, g, d.index[0], d.index[1])
    return None, damaged


def _tomo_task(
    item, *, recon_path, center_m, device, fft_workers, fbp, slice_background=tomography.DEFAULT_SLICE_BACKGROUND
):
    """FBP of one (position, row block); returns the damaged chunks it found (then nothing is
    written and the block stays not done)."""
    import zarr

    from pwf_dask.backend import FFT

    p, b = item
    g = zarr.open_group(str(recon_path), mode="r+", use_consolidated=False)
    rb = g["delta"].chunks[1]
    ny = g["delta"].shape[1]
    rows = slice(b * rb, min(ny, (b + 1) * rb))
    xp = resolve_device(device)
    fft = FFT.for_module(xp, worker_fft_threads(fft_workers))
    angles = g["angle"][...]
    pix = float(g.attrs["pixel_size_m"])
    wl = wavelength_m(float(g.attrs["energy_eV"]))
    sinograms = {}
    for name in ("phase", "attenuation"):  # both checked before anything is written
        sinograms[name], damaged = _read_sinogram(g, str(recon_path), name, p, rows, b)
        if damaged:
            return [str(d) for d in damaged]
    # one volume at a time: delta is written before beta's FBP (the task's peak, issue #29)
    far = None
    for name, out, sign in (("phase", "delta", -1.0), ("attenuation", "beta", 1.0)):
        sino = xp.asarray(sinograms.pop(name))
        slices = tomography.back_projection(sino, angles, pix, center_m, fft=fft, method=fbp)
        del sino
        slices *= np.float32(sign * wl / (2 * np.pi))  # tomography.to_refractive_index, in place
        if out == "delta" and slice_background == "auto":  # beta's fit goes where delta's does
            far = tomography.far_background_masks(slices)
        # on the FBP's device, then to the host
        slices = tomography.corrected_slices(slices, out, slice_background, far)
        g[out][p, rows] = to_numpy(slices).astype(np.float32, copy=False)
        del slices
    g["tomo_done"][p, b] = 1
    return []


class RetrievalDamaged(scan_io.ScanError):
    """Tomography found retrieved chunks missing or damaged; they are marked not done."""


def rotation_center(recon_path) -> float:
    """Rotation axis from the -phase sinograms of the middle row block of position 0: from a
    180-degree pair when the scan has one, else from the centre-of-mass sinusoid."""
    import zarr

    g = zarr.open_group(str(recon_path), mode="r", use_consolidated=False)
    ny = g["phase"].shape[2]
    rb = g["phase"].chunks[2]
    mid = (ny // 2) // rb * rb
    sino = -integrity.read_checked(recon_path, g["phase"], "phase", (0, slice(None), slice(mid, mid + rb)))
    angles, pix = g["angle"][...], float(g.attrs["pixel_size_m"])
    c = tomography.rotation_center_from_opposite(sino, angles, pix)
    return c if c is not None else tomography.estimate_rotation_center(sino, angles, pix)


def _check_center(center_m: float, g) -> None:
    """One line for a given rotation centre that is not a number or lies off the detector
    (the tomograms would be NaN or empty), before anything is written."""
    half_width_m = 0.5 * g["phase"].shape[-1] * float(g.attrs["pixel_size_m"])
    if not abs(float(center_m)) < half_width_m:
        raise ValueError(
            f"center_m must be a finite offset inside the frame (|c| < {half_width_m * 1e6:.2f} µm from its centre), "
            f"got {float(center_m) * 1e6:g} µm"
        )


def tomo_scan(
    recon_path,
    *,
    scheduler: str = "threads",
    device: str = "cpu",
    center_m: float | None = None,
    runner: Runner | None = None,
    fbp: str = "auto",
    slice_background: str = tomography.DEFAULT_SLICE_BACKGROUND,
) -> dict:
    """Tomography stage: FBP of phase and attenuation per (position, row block) -> delta, beta.

    ``fbp`` (:data:`tomography.FBP_METHODS`): "auto" is gridding where its NUFFT is installed.
    ``slice_background`` (:data:`tomography.SLICE_BACKGROUNDS`): which tomograms get the
    quadratic background fit after the FBP (Methods): "auto", the default, fits both where
    the slice has sample-free pixels beyond the sample's halo; "quadratic" (the paper's)
    wherever it has any. Both are recorded; tomograms made otherwise are made again, never mixed.
    """
    import zarr

    check_scheduler(scheduler)
    tomography.check_slice_background(slice_background)
    fbp = tomography.resolve_fbp(fbp, resolve_device(device) if "://" not in scheduler else np)
    path = str(Path(recon_path).resolve())
    if not Path(path).exists():
        raise scan_io.ScanError(f"{path}: no such reconstruction store; run 'pwf-dask retrieve' first")
    g = zarr.open_group(path, mode="r+", use_consolidated=False)
    if "phase" not in g:
        raise scan_io.ScanError(f"{path}: not a reconstruction store (no 'phase')")
    _check_retrieved(path, g)
    estimated = center_m is None
    if not estimated:
        _check_center(center_m, g)
    if estimated:
        try:
            center_m = rotation_center(path)
        except integrity.DamagedChunk as exc:
            integrity.reset_projection(path, g, exc.index[0], exc.index[1])
            raise RetrievalDamaged(
                f"{exc} (projection {exc.index[:2]}); marked not done: rerun 'pwf-dask retrieve' (or 'run')"
            ) from None
    _create_tomograms(g, float(center_m), estimated, fbp, slice_background)
    own = runner is None
    runner = runner or Runner(scheduler)
    try:
        done = _verified_blocks(runner, path, g)
        todo = [(int(p), int(b)) for p, b in zip(*np.nonzero(done == 0))]
        where = "estimated" if estimated else "given"
        _say(f"tomo: rotation centre {center_m * 1e6:+.2f} µm ({where}); {len(todo)} of {done.size} blocks to compute")
        t0 = time.perf_counter()
        found = runner.map(
            _tomo_task,
            todo,
            label="tomo",
            unit="slice blocks",
            count=partial(_count_done, path, "tomo_done", 1),
            total=done.size,
            recon_path=path,
            center_m=float(center_m),
            fbp=fbp,
            slice_background=slice_background,
            device=device,
            fft_workers=runner.fft_workers(),
        )
    finally:
        if own:
            runner.close()
    damaged = [d for block in found for d in block]
    if damaged:
        raise RetrievalDamaged(
            f"{len(damaged)} retrieved chunks missing or damaged (first: {damaged[0]}); their projections are "
            "marked not done: rerun 'pwf-dask retrieve' (or 'run') to recompute them"
        )
    wall = time.perf_counter() - t0
    if todo:
        g.attrs["tomo_wall_s"] = wall
    scan_io.consolidate(path)
    return {"computed": len(todo), "rotation_center_m": float(center_m), "wall_s": wall}


def _check_retrieved(path: str, g) -> None:
    """Every projection retrieved and its chunks there; a lost one is marked not done and named."""
    done, damaged = integrity.read_bookkeeping(path, g, "iterations")
    lost = integrity.missing_projection_chunks(path, g, done)
    for p, a in lost:
        integrity.reset_projection(path, g, p, a)
    if damaged or lost:
        first = str(damaged[0]) if damaged else f"{lost[next(iter(lost))][0][0]} chunk of projection {next(iter(lost))}"
        raise RetrievalDamaged(
            f"{path}: {len(damaged) + len(lost)} retrieved projections missing or damaged (first: {first}); "
            "marked not done: rerun 'pwf-dask retrieve' (or 'run') to recompute them"
        )
    missing = int((done < 0).sum())
    if missing:
        raise scan_io.ScanError(
            f"{path}: retrieval incomplete ({missing} projections missing); rerun 'pwf-dask retrieve'"
        )
    if g["phase"].shape[1] < 2:
        raise scan_io.ScanError(f"{path}: one angle; tomography needs >= 2 (its phase and attenuation are complete)")


def _create_tomograms(
    g,
    center_m: float,
    estimated: bool,
    fbp: str = "backproject",
    slice_background: str = tomography.DEFAULT_SLICE_BACKGROUND,
) -> None:
    """The delta/beta arrays and their bookkeeping, new unless they exist for this centre, FBP
    and background fit (their attributes are written last: an interrupted creation is made again)."""
    same_fbp = g.attrs.get("fbp", "backproject") == fbp  # stores before issue #31 were backprojected
    same_fit = g.attrs.get("slice_background", "quadratic") == slice_background  # and before session 74 fitted both
    if "delta" in g and float(g.attrs.get("rotation_center_m", np.nan)) == center_m and same_fbp and same_fit:
        return
    npos, _, ny, nx = g["phase"].shape
    rb = g["phase"].chunks[2]
    coords = (np.arange(nx) - (nx - 1) / 2) * float(g.attrs["pixel_size_m"])
    scan_io.create_variable(g, "v", (nx,), (nx,), ("v",), "float64", 0.0, coords)
    scan_io.create_variable(g, "u", (nx,), (nx,), ("u",), "float64", 0.0, coords)
    for name in ("delta", "beta"):
        scan_io.create_variable(
            g, name, (npos, ny, nx, nx), (1, rb, nx, nx), ("position", "y", "v", "u"), "float32", np.nan
        )
    scan_io.create_variable(g, "tomo_done", (npos, -(-ny // rb)), (1, 1), ("position", "row_block"), "int8", 0)
    g.attrs.update(
        {
            "rotation_center_m": center_m,
            "rotation_center_estimated": estimated,
            "filter": "ram-lak",
            "fbp": fbp,
            "slice_background": slice_background,
            "background_removal": tomography.SLICE_BACKGROUNDS[slice_background],
        }
    )


def _verified_blocks(runner, path: str, g) -> np.ndarray:
    """``tomo_done`` as trusted: a block marked done counts only if its delta/beta chunks are
    there and decode; any other is named, marked not done and recomputed."""
    done, damaged = integrity.read_bookkeeping(path, g, "tomo_done")
    _report_damage("tomo", damaged, "its row block is recomputed")
    for p, b in integrity.missing_block_chunks(path, done):
        _say(f"tomo: {path}: delta/beta chunk of row block ({p}, {b}) is missing: recomputed")
        integrity.reset_block(path, g, p, b)
        done[p, b] = 0
    stored = [integrity.block_chunks(int(p), int(b)) for p, b in zip(*np.nonzero(done >= 1))]
    for fault in _decode_all(runner, path, "row block", stored):
        _say(f"tomo: {fault}: its row block is recomputed")
        integrity.reset_block(path, g, *fault.index[:2])
        done[fault.index[:2]] = 0
    return done


# --- FSC --------------------------------------------------------------------------------


#: The FSC stage compares a central sub-volume of at most this many rows (y) and pixels across
#: (v and u). Both half-tomograms of a K = 1 scan are made in the client: whole, 801 x 32 x 2560
#: took 11.5 GB, and a paper-size 2160-row scan would need ~0.8 TB (issue #29). Only rows are
#: cut for a camera's width: the even/odd halves share the diffuser's fixed-pattern errors,
#: which back-project to rings, strongest at the centre, so a central 1024^2 crop of that scan
#: read 1.4 µm (the Nyquist limit) against 5.7 µm for whole slices. Scans within the bounds are
#: compared whole; a cut axis is tapered (:func:`_sub_volume_fsc`).
FSC_MAX_ROWS = 64
FSC_MAX_PX = 4096
#: rows of full slices reconstructed at a time before the crop (8 x 2560^2 doubles: 420 MB)
_FSC_BLOCK_ROWS = 8


def fsc_region(n_rows: int, n_px: int) -> tuple[slice, slice]:
    """(rows, pixels) of the central FSC sub-volume (:data:`FSC_MAX_ROWS`, :data:`FSC_MAX_PX`)."""
    r, c = min(n_rows, FSC_MAX_ROWS), min(n_px, FSC_MAX_PX)
    return slice((n_rows - r) // 2, (n_rows - r) // 2 + r), slice((n_px - c) // 2, (n_px - c) // 2 + c)


def _sub_volume_fsc(a, b, pix: float, full_shape: tuple[int, int, int]):
    """Eq. (FSC) of two sub-volumes; an axis cut out of a larger volume is tapered first (a
    Tukey window, 10 % each side, the same on both), else the cut's sharp edges, the same in
    both volumes, correlate at every frequency (measured: 1.4 µm, the Nyquist limit, on the
    801 x 32 x 2560 scan cut to 1024^2 without the taper)."""
    from scipy.signal.windows import tukey

    for axis, (n, whole) in enumerate(zip(np.shape(a), full_shape)):
        if n < whole:
            w = tukey(n, 0.2).reshape([-1 if k == axis else 1 for k in range(len(full_shape))])
            a, b = a * w, b * w
    return fsc.fourier_shell_correlation(a, b, pix)


def _stored_far_masks(path, g, p, rows: slice) -> dict:
    """Under "auto", :func:`tomography.far_background_masks` of the stored delta's slices of
    position ``p``, per FSC block of rows (the start row its key); else empty."""
    if g.attrs.get("slice_background", "quadratic") != "auto":
        return {}
    stored = integrity.read_checked(path, g["delta"], "delta", (p, rows))
    return {
        s: tomography.far_background_masks(stored[s : s + _FSC_BLOCK_ROWS])
        for s in range(0, len(stored), _FSC_BLOCK_ROWS)
    }


def _even_odd_volumes(path, g, name, p, center_m, wl, sign, rows: slice, px: slice, far: dict):
    """delta (or beta) from the even and the odd angles alone, on the FSC sub-volume; each
    block of full slices is reconstructed and background-corrected before the crop, as the
    store's tomograms were (under "auto" where ``far``, :func:`_stored_far_masks`, says)."""
    angles = g["angle"][...]
    order = np.argsort(angles)
    halves = (np.sort(order[0::2]), np.sort(order[1::2]))
    pix = float(g.attrs["pixel_size_m"])
    mode = g.attrs.get("slice_background", "quadratic")
    volume = "delta" if name == "phase" else "beta"
    sino = integrity.read_checked(path, g[name], name, (p, slice(None), rows))
    vols = []
    for idx in halves:
        blocks = []
        for start in range(0, sino.shape[1], _FSC_BLOCK_ROWS):
            block = sino[idx, start : start + _FSC_BLOCK_ROWS]
            vol = tomography.back_projection(
                block, angles[idx], pix, center_m, method=g.attrs.get("fbp", "backproject")
            )
            vol = tomography.corrected_slices(sign * wl / (2 * np.pi) * vol, volume, mode, far.get(start))
            blocks.append(vol[:, px, px].astype(np.float32))
        vols.append(np.concatenate(blocks))
    return vols


def fsc_scan(recon_path, *, split: str = "auto", criterion: str = "1/4", pairs: int = 5, seed: int = 0) -> dict:
    """FSC stage: between tomograms of diffuser positions (random pairs, averaged; the
    paper's procedure) or of even/odd angle halves (K = 1), plus against the truth of a
    simulated scan (criterion 1/2). Writes fsc_delta, fsc_beta (split, frequency)."""
    import zarr

    path = str(recon_path)
    g = zarr.open_group(path, mode="r+", use_consolidated=False)
    if "phase" not in g:
        raise scan_io.ScanError(f"{path}: not a reconstruction store (no 'phase')")
    if g["phase"].shape[1] < 2:
        raise scan_io.ScanError(f"{path}: one angle; FSC needs tomograms, from >= 2 angles")
    if "delta" not in g or int(g["tomo_done"][...].min()) == 0:
        raise scan_io.ScanError(f"{path}: tomograms incomplete; run 'pwf-dask tomo' first")
    if criterion not in fsc.CRITERIA:
        raise ValueError(f"unknown criterion {criterion!r}; choose one of {', '.join(fsc.CRITERIA)}")
    npos = g["delta"].shape[0]
    if split == "auto":
        split = "positions" if npos >= 2 else "even-odd"
    if split == "positions" and npos < 2:
        raise ValueError("FSC split 'positions' needs K >= 2 diffuser positions; use --split even-odd")
    if split not in ("positions", "even-odd"):
        raise ValueError(f"unknown FSC split {split!r}: use positions or even-odd")
    pix = float(g.attrs["pixel_size_m"])
    rows, px = fsc_region(g["delta"].shape[1], g["delta"].shape[2])
    t0 = time.perf_counter()
    if split == "positions":
        f, n, curves, labels = _position_pair_curves(path, g, rows, px, pairs, seed)
    else:
        f, n, curves, labels = _even_odd_curves(path, g, rows, px)
    summary = {"split": split, "labels": labels, **_write_fsc(g, f, n, curves, labels, split, criterion)}
    if "simulation_phantom" in g.attrs:
        summary.update(_fsc_truth(g, f, pix, rows, px))
    g.attrs["fsc_wall_s"] = time.perf_counter() - t0
    scan_io.consolidate(path)
    return summary


def _position_pair_curves(path, g, rows: slice, px: slice, pairs: int, seed: int):
    """(frequencies, shell counts, {delta, beta: FSC curves}, labels) between the tomograms of
    ``pairs`` random pairs of diffuser positions (all pairs where there are no more)."""
    npos = g["delta"].shape[0]
    pix = float(g.attrs["pixel_size_m"])
    all_pairs = [(i, j) for i in range(npos) for j in range(i + 1, npos)]
    rng = np.random.default_rng(seed)
    chosen = (
        all_pairs
        if len(all_pairs) <= pairs
        else [all_pairs[k] for k in rng.choice(len(all_pairs), pairs, replace=False)]
    )
    curves: dict[str, list] = {"delta": [], "beta": []}
    for i, j in chosen:
        for name in ("delta", "beta"):
            vi, vj = (integrity.read_checked(path, g[name], name, (k, rows, px, px)) for k in (i, j))
            f, c, n = _sub_volume_fsc(vi, vj, pix, g["delta"].shape[1:])
            curves[name].append(c)
    return f, n, curves, [f"positions {i}-{j}" for i, j in chosen]


def _even_odd_curves(path, g, rows: slice, px: slice):
    """(frequencies, shell counts, {delta, beta: FSC curves}, labels) between the tomograms of
    each position's even and odd angles (K = 1)."""
    pix = float(g.attrs["pixel_size_m"])
    wl = wavelength_m(float(g.attrs["energy_eV"]))
    center = float(g.attrs["rotation_center_m"])
    curves: dict[str, list] = {"delta": [], "beta": []}
    labels = []
    for p in range(g["delta"].shape[0]):
        far = _stored_far_masks(path, g, p, rows)  # both volumes' fits go where delta's did
        for name, src, sign in (("delta", "phase", -1.0), ("beta", "attenuation", 1.0)):
            a, b = _even_odd_volumes(path, g, src, p, center, wl, sign, rows, px, far)
            f, c, n = _sub_volume_fsc(a, b, pix, g["delta"].shape[1:])
            curves[name].append(c)
        labels.append(f"position {p} even-odd angles")
    return f, n, curves, labels


def _write_fsc(g, f, n, curves: dict, labels: list, split: str, criterion: str) -> dict:
    """fsc_delta and fsc_beta (split, frequency) with their resolutions by three criteria in
    the attributes; returns {delta, beta: the resolution by ``criterion`` (m)}."""
    nf = len(f)
    scan_io.create_variable(g, "split", (len(labels),), (len(labels),), ("split",), "int64", 0, np.arange(len(labels)))
    scan_io.create_variable(g, "frequency", (nf,), (nf,), ("frequency",), "float64", 0.0, f)
    summary = {}
    for name in ("delta", "beta"):
        arr = np.array(curves[name])
        mean = arr.mean(axis=0)
        res = {c: fsc.resolution(f, mean, n, c) for c in ("1/4", "1/7", "half-bit")}
        a = scan_io.create_variable(
            g, f"fsc_{name}", arr.shape, arr.shape, ("split", "frequency"), "float64", np.nan, arr
        )
        a.attrs.update(
            {
                "criterion": criterion,
                "resolution_m": res[criterion],
                "split": split,
                "labels": json.dumps(labels),
                "resolution_m_1_4": res["1/4"],
                "resolution_m_1_7": res["1/7"],
                "resolution_m_half_bit": res["half-bit"],
            }
        )
        summary[name] = res[criterion]
    return summary


def _fsc_truth(g, freq, pix, rows: slice, px: slice) -> dict:
    """FSC of each position's tomograms against the simulated truth (criterion 1/2), on the
    FSC sub-volume."""
    from pwf_dask.simulation import phantom_from_json, refractive_index_volume

    phantom = phantom_from_json(g.attrs["simulation_phantom"])
    truth = refractive_index_volume(phantom, g["y"][rows], g["v"][px], g["u"][px], float(g.attrs["energy_eV"]))
    npos = g["delta"].shape[0]
    out = {}
    for name, t in zip(("delta", "beta"), truth):
        curves = []
        for p in range(npos):
            f, c, n = _sub_volume_fsc(g[name][p, rows, px, px], t, pix, g["delta"].shape[1:])
            curves.append(c)
        arr = np.array(curves)
        res = fsc.resolution(f, arr.mean(axis=0), n, "1/2")
        a = scan_io.create_variable(
            g, f"fsc_{name}_truth", arr.shape, arr.shape, ("position", "frequency"), "float64", np.nan, arr
        )
        a.attrs.update({"criterion": "1/2", "resolution_m": res})
        out[f"{name}_truth"] = res
    return out


def _n_angles(recon_path) -> int:
    import zarr

    return int(zarr.open_group(str(recon_path), mode="r", use_consolidated=False)["phase"].shape[1])


def run_scan(
    scan_path,
    recon_path,
    *,
    scheduler: str = "threads",
    device: str = "cpu",
    split: str = "auto",
    center_m: float | None = None,
    runner: Runner | None = None,
    fbp: str = "auto",
    slice_background: str = tomography.DEFAULT_SLICE_BACKGROUND,
    **retrieve_options,
) -> dict:
    """All stages on one scheduler connection: retrieve, tomo, fsc. A single-angle scan (a
    radiograph) stops after retrieval: ``tomo`` and ``fsc`` are then None."""
    tomography.resolve_fbp(fbp)  # a bad name fails before anything is written
    tomography.check_slice_background(slice_background)
    own = runner is None
    runner = runner or Runner(scheduler)
    tomo = dict(scheduler=scheduler, device=device, center_m=center_m, runner=runner, fbp=fbp)
    try:
        r = retrieve_scan(scan_path, recon_path, scheduler=scheduler, device=device, runner=runner, **retrieve_options)
        if _n_angles(recon_path) < 2:
            return {"retrieve": r, "tomo": None, "fsc": None}
        try:
            t = tomo_scan(recon_path, slice_background=slice_background, **tomo)
        except RetrievalDamaged as exc:  # recompute what tomography found damaged, once
            _say(f"run: {exc}; recomputing")
            again = retrieve_scan(
                scan_path, recon_path, scheduler=scheduler, device=device, runner=runner, **retrieve_options
            )
            r["computed"] += again["computed"]
            t = tomo_scan(recon_path, slice_background=slice_background, **tomo)
    finally:
        if own:
            runner.close()
    f = fsc_scan(recon_path, split=split)
    return {"retrieve": r, "tomo": t, "fsc": f}
