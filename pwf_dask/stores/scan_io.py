"""Scan and reconstruction stores (docs/scan-format.md §1-2): validation, flat/dark correction, layout.

A scan is opened with xarray and validated completely before anything is written; every
problem is one line naming it (:class:`ScanError`). The reconstruction store is laid out for
the stages that follow:

* ``phase``/``attenuation`` (position, angle, y, x) are chunked one angle by a block of
  rows: a retrieval task writes whole chunks of its own angle only (no two tasks ever share
  a chunk, so nothing is corrupted), and a sinogram slab (all angles, one row block) is read
  as one chunk per angle, with no in-memory rechunk of the whole scan;
* per-projection diagnostics (position, angle) are one element per chunk, for the same
  reason; ``iterations`` = -1 marks an angle not done yet, which is what resuming reads;
* ``delta``/``beta`` (position, y, v, u) are chunked by the same row blocks.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pwf_dask.stores import integrity

REQUIRED_ATTRS = (
    "energy_eV",
    "pixel_size_m",
    "sample_diffuser_distance_m",
    "diffuser_detector_distance_m",
)


class ScanError(ValueError):
    """A scan that breaks docs/scan-format.md §1; the message is one line naming the problem."""


@dataclass
class ScanInfo:
    """What the stages need to know about a validated scan."""

    path: str
    n_positions: int
    angles_deg: np.ndarray
    shape: tuple[int, int]
    x_m: np.ndarray
    y_m: np.ndarray
    energy_eV: float
    pixel_size_m: float
    sample_diffuser_distance_m: float
    diffuser_detector_distance_m: float
    coherence_length_x_m: float | None
    coherence_length_y_m: float | None
    flat_dark_corrected: bool
    has_flat: bool
    has_dark: bool
    attrs: dict = field(default_factory=dict)
    #: optional, not in docs/scan-format.md §1: the diffuser this far upstream of the sample (L1 = 0)
    diffuser_upstream_m: float = 0.0


def _attr_float(attrs, name, path):
    if name not in attrs:
        raise ScanError(f"{path}: missing attribute {name!r}")
    raw = attrs[name]
    # a number, not text that looks like one, nor a boolean (which float() would take as 0/1)
    if isinstance(raw, (bool, np.bool_)) or not isinstance(raw, (int, float, np.integer, np.floating)):
        raise ScanError(f"{path}: attribute {name!r} is not a number: {raw!r} ({type(raw).__name__})")
    value = float(raw)
    if not np.isfinite(value):
        raise ScanError(f"{path}: attribute {name!r} is not finite")
    return value


def correct(raw, flat=None, dark=None, corrected: bool = False):
    """Flat/dark correction (I - dark) / (flat - dark) as float32; identity when ``corrected``."""
    a = np.asarray(raw, dtype=np.float32)
    if corrected:
        return a
    if dark is not None:
        a = a - np.asarray(dark, np.float32)
    if flat is not None:
        den = np.asarray(flat, np.float32) - (0 if dark is None else np.asarray(dark, np.float32))
        a = a / den
    return a


def _check_layout(path: str) -> None:
    """Variables, dims and shapes from the Zarr metadata, before xarray (which cannot even open
    a store whose arrays disagree on a dimension's length)."""
    import zarr

    try:
        g = zarr.open_group(path, mode="r", use_consolidated=False)
    except Exception as exc:
        raise ScanError(f"{path}: not a Zarr store ({type(exc).__name__})") from None
    names = set(g.array_keys())
    for name in ("projections", "reference"):
        if name not in names:
            raise ScanError(f"{path}: missing variable {name!r}")

    def dims(name):
        d = getattr(g[name].metadata, "dimension_names", None) or g[name].attrs.get("_ARRAY_DIMENSIONS")
        return tuple(d) if d else None

    if dims("projections") != ("position", "angle", "y", "x"):
        raise ScanError(f"{path}: projections has dims {dims('projections')}, expected (position, angle, y, x)")
    if dims("reference") != ("position", "y", "x"):
        raise ScanError(f"{path}: reference has dims {dims('reference')}, expected (position, y, x)")
    npos, nang, ny, nx = g["projections"].shape
    if tuple(g["reference"].shape) != (npos, ny, nx):
        raise ScanError(
            f"{path}: reference shape {tuple(g['reference'].shape)} does not match projections (position, y, x) = "
            f"{(npos, ny, nx)}"
        )
    for name in ("flat", "dark"):
        if name in names and tuple(g[name].shape) != (ny, nx):
            raise ScanError(f"{path}: {name} shape {tuple(g[name].shape)} is not (y, x) = {(ny, nx)}")


def open_scan(path: str | Path, check_values: bool = True):
    """Open and validate a scan store. Returns (dataset, ScanInfo); raises ScanError."""
    import xarray as xr

    path = str(path)
    if not Path(path).exists():
        raise ScanError(f"{path}: no such scan store")
    _check_layout(path)
    try:
        with warnings.catch_warnings():
            # a store without consolidated metadata (another writer's) is read as it is
            warnings.filterwarnings("ignore", message="Failed to open Zarr store with consolidated metadata")
            ds = xr.open_zarr(path, consolidated=None)
    except Exception as exc:  # zarr/xarray raise many types for a broken store
        raise ScanError(f"{path}: not a readable Zarr dataset ({type(exc).__name__}: {exc})") from None
    npos, nang, ny, nx = ds["projections"].shape
    angles = _checked_arrays(ds, path)
    attrs = dict(ds.attrs)
    vals, upstream, coh = _checked_optics(attrs, path)
    corrected = attrs.get("flat_dark_corrected", False)
    if not isinstance(corrected, (bool, np.bool_)):
        raise ScanError(
            f"{path}: attribute 'flat_dark_corrected' must be a boolean (true/false), got {corrected!r} "
            f"({type(corrected).__name__})"
        )
    corrected = bool(corrected)
    p = vals["pixel_size_m"]
    x = np.asarray(ds["x"].values, np.float64) if "x" in ds.coords else (np.arange(nx) - (nx - 1) / 2) * p
    y = np.asarray(ds["y"].values, np.float64) if "y" in ds.coords else (np.arange(ny) - (ny - 1) / 2) * p
    info = ScanInfo(
        path=path,
        n_positions=npos,
        angles_deg=angles,
        shape=(ny, nx),
        x_m=x,
        y_m=y,
        energy_eV=vals["energy_eV"],
        pixel_size_m=p,
        sample_diffuser_distance_m=vals["sample_diffuser_distance_m"],
        diffuser_detector_distance_m=vals["diffuser_detector_distance_m"],
        coherence_length_x_m=coh[0],
        coherence_length_y_m=coh[1],
        flat_dark_corrected=corrected,
        has_flat="flat" in ds,
        has_dark="dark" in ds,
        attrs=attrs,
        diffuser_upstream_m=upstream,
    )
    if check_values:
        check_scan_values(ds, info)
    return ds, info


def _checked_arrays(ds, path: str) -> np.ndarray:
    """The angles (degrees) of a scan whose arrays are usable: finite, distinct angles, a
    frame of at least 16 x 16 and real intensities; else one ScanError line."""
    npos, nang, ny, nx = ds["projections"].shape
    if "angle" not in ds.coords:
        raise ScanError(f"{path}: missing coordinate 'angle' (degrees)")
    angles = np.asarray(ds["angle"].values, dtype=np.float64)
    if not np.all(np.isfinite(angles)):
        raise ScanError(f"{path}: angle coordinate has non-finite values")
    if npos < 1 or nang < 1 or min(ny, nx) < 16:
        raise ScanError(
            f"{path}: projections {ds['projections'].shape} too small (need >= 1 position and angle, 16 x 16 px)"
        )
    for name in ("projections", "reference", "flat", "dark"):
        if name in ds and not (np.issubdtype(ds[name].dtype, np.integer) or np.issubdtype(ds[name].dtype, np.floating)):
            raise ScanError(f"{path}: {name} has dtype {ds[name].dtype}; intensities are real numbers (int or float)")
    if nang > 1 and np.ptp(angles) == 0:
        raise ScanError(f"{path}: all {nang} angles are {angles[0]:g} deg; a scan rotates the sample")
    return angles


#: optional, not in docs/scan-format.md §1: the raw counts at which the detector saturates
#: (e.g. 4095 for a 12-bit camera); without it an integer frame's type maximum is taken
FULL_SCALE_ATTR = "detector_full_scale_counts"


def _checked_optics(attrs: dict, path: str) -> tuple[dict, float, list]:
    """(the contract's geometry attributes, the upstream distance, the coherence lengths or
    None), each a plausible number (:class:`~pwf_dask.physics.geometry.Geometry`)."""
    from pwf_dask.physics.geometry import Geometry
    from pwf_dask.physics.optics import check_plausible_geometry

    vals = {name: _attr_float(attrs, name, path) for name in REQUIRED_ATTRS}
    upstream = _attr_float(attrs, "diffuser_upstream_m", path) if "diffuser_upstream_m" in attrs else 0.0
    coh = []
    for name in ("coherence_length_x_m", "coherence_length_y_m"):
        if name in attrs:
            c = _attr_float(attrs, name, path)
            if c < 0:
                raise ScanError(f"{path}: {name} must be >= 0, got {c}")
            coh.append(c)
        else:
            coh.append(None)
    if FULL_SCALE_ATTR in attrs and not _attr_float(attrs, FULL_SCALE_ATTR, path) > 0:
        raise ScanError(f"{path}: {FULL_SCALE_ATTR} must be > 0, got {attrs[FULL_SCALE_ATTR]}")
    try:
        upstream = Geometry(**vals, diffuser_upstream_m=upstream).diffuser_upstream_m
        check_plausible_geometry(coherence_length_x_m=coh[0], coherence_length_y_m=coh[1])
    except ValueError as exc:
        raise ScanError(f"{path}: {exc}") from None
    return vals, upstream, coh


def check_scan_values(ds, info: ScanInfo) -> None:
    """Refuse non-finite or negative intensities after correction (a chunked Dask pass, reduced
    per frame so that the refusal names the first bad frame's position and angle), and missing
    or undecodable chunks (named)."""
    _check_chunks_exist(info.path)
    try:
        _check_values(ds, info)
    except ScanError:
        raise
    except Exception:  # a chunk that does not decode: name it
        import zarr

        g = zarr.open_group(info.path, mode="r")
        for name in ("flat", "dark", "reference", "projections"):
            if name in g:
                for index in integrity.chunk_grid(g[name]):
                    try:
                        integrity.read_chunk(info.path, g[name], name, index)
                    except integrity.DamagedChunk as exc:
                        raise ScanError(f"{exc}; restore or re-ingest that frame") from None
        raise


def _check_chunks_exist(path: str) -> None:
    """Every chunk of the scan's frames is stored (one stat each): a lost file is never read
    as zeros. Only for arrays pwf-dask wrote (checksummed, every chunk stored): other writers
    may leave out a chunk equal to the fill value."""
    import zarr

    g = zarr.open_group(path, mode="r")
    for name in ("flat", "dark", "reference", "projections"):
        if name in g and integrity.stores_every_chunk(g[name]):
            for index in integrity.chunk_grid(g[name]):
                if not integrity.chunk_path(path, name, index, g[name]).exists():
                    raise ScanError(f"{path}: {name} chunk {index} is missing; restore or re-ingest that frame")


def _check_values(ds, info: ScanInfo) -> None:
    """Every frame holds more than one value, and is finite and non-negative after flat/dark
    correction; read once, chunk by chunk.

    The arrays are xarray's lazy ones: NumPy's reductions dispatch to them, and one
    ``Dataset.compute`` reads each chunk once for all checks."""

    import xarray as xr

    flat = ds["flat"].data if info.has_flat else None
    dark = ds["dark"].data if info.has_dark else None
    for name in ("reference", "projections"):
        raw = ds[name].data
        cor = raw.astype(np.float32)
        if not info.flat_dark_corrected:
            if dark is not None:
                cor = cor - dark.astype(np.float32)
            if flat is not None:
                den = flat.astype(np.float32) - (0 if dark is None else dark.astype(np.float32))
                with np.errstate(divide="ignore", invalid="ignore"):
                    cor = cor / den
        frames = [f"d{i}" for i in range(cor.ndim - 2)]
        with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN frame: named below
            checks = xr.Dataset(
                {
                    "blank": (frames, (raw == raw[..., :1, :1]).all(axis=(-2, -1))),
                    "finite": (frames, np.isfinite(cor).all(axis=(-2, -1))),
                    "minimum": (frames, np.nanmin(cor, axis=(-2, -1))),
                }
            ).compute(scheduler="threads")
        for bad, what in (
            # no speckle: an empty exposure, or a chunk that another writer left out (zarr
            # reads it as the fill value)
            (checks["blank"].values, "one value in every pixel (a blank frame, or a chunk not in the store)"),
            (~checks["finite"].values, "non-finite values (NaN or inf) after flat/dark correction"),
            (checks["minimum"].values < 0, "negative values after flat/dark correction"),
        ):
            if bad.any():
                where = np.argwhere(bad)[0]
                frame = f"position {where[0]}" + (
                    f", angle {where[1]} ({float(info.angles_deg[where[1]]):g} deg)" if name == "projections" else ""
                )
                raise ScanError(f"{info.path}: {name} at {frame} has {what}")


def row_block(ny: int, nx: int) -> int:
    """Rows per chunk: ~64k pixels (a 25-row slab of a 2560-wide frame, 410 MB over 801 angles)."""
    return int(min(ny, max(4, 65536 // max(nx, 1))))


#: CF-style ``units`` and ``long_name`` of every coordinate and variable the stores hold
#: (``"1"``: dimensionless; counts carry the detector's "count"), so that xarray's plots and
#: other tools label their axes. ``tomo_done`` is the resume bookkeeping of the tomography stage.
VARIABLE_ATTRS: dict[str, tuple[str, str]] = {
    "position": ("1", "diffuser position index"),
    "angle": ("degree", "rotation angle"),
    "y": ("m", "detector row coordinate (rotation axis direction)"),
    "x": ("m", "detector column coordinate"),
    "u": ("m", "sample coordinate across the beam at angle 0"),
    "v": ("m", "sample coordinate along the beam at angle 0"),
    "projections": ("count", "sample speckle images"),
    "reference": ("count", "reference speckle images without the sample"),
    "flat": ("count", "flat field without diffuser or sample"),
    "dark": ("count", "dark field"),
    "phase": ("rad", "projected phase (Im psi)"),
    "attenuation": ("1", "projected amplitude attenuation (-Re psi)"),
    "iterations": ("1", "PWF iterations"),
    "converged": ("1", "stop rule met before max_iter"),
    "residual_rmse": ("percent", "RMS data residual over the mean reference"),
    "outlier_pixels": ("1", "pixels repaired as outliers"),
    "retrieval_seconds": ("s", "wall time of the projection's retrieval task (reading to writing)"),
    "diffuser": ("1", "fitted diffuser transmission t_r per position (real, imaginary), computational grid"),
    "preview_residual": ("percent", "data residual |y - f| of the first angle's projection (preview)"),
    "diffuser_drift_y_px": ("pixel", "measured speckle drift against the reference, rows"),
    "diffuser_drift_x_px": ("pixel", "measured speckle drift against the reference, columns"),
    "speckle_shift_over_grain": ("1", "99th percentile of the phase's speckle shift over the speckle grain (PWF)"),
    "speckle_visibility": ("1", "reference speckle's rms over its mean, photon noise removed (PWF)"),
    "sample_misfit": ("1", "data misfit inside the sample over its background's, on the photon-noise scale (PWF)"),
    "position_disagreement": (
        "1",
        "rms of a position's phase less the other positions' over the rms of their mean, in the sample (PWF, K >= 2)",
    ),
    "background_plane_phase": ("rad", "plane subtracted from the phase (constant, row and column slopes per frame)"),
    "background_plane_attenuation": ("1", "plane subtracted from the attenuation (constant, row and column slopes)"),
    "delta": ("1", "refractive index decrement delta"),
    "beta": ("1", "absorption index beta"),
    "tomo_done": ("1", "bookkeeping: 1 where this row block's slices are reconstructed (resume)"),
    "split": ("1", "FSC split index"),
    "frequency": ("1/m", "spatial frequency"),
    "fsc_delta": ("1", "Fourier shell correlation of delta"),
    "fsc_beta": ("1", "Fourier shell correlation of beta"),
    "fsc_delta_truth": ("1", "Fourier shell correlation of delta with the ground truth"),
    "fsc_beta_truth": ("1", "Fourier shell correlation of beta with the ground truth"),
}


def create_variable(group, name, shape, chunks, dims, dtype, fill, data=None):
    """A checksummed array ``name`` in ``group`` with its dimension names and, for a variable of
    docs/scan-format.md, its units and long name (replacing any of that name); ``data`` fills it."""
    arr = group.create_array(
        name,
        shape=shape,
        chunks=chunks,
        dtype=dtype,
        fill_value=fill,
        dimension_names=dims,
        overwrite=True,
        compressors=integrity.chunk_compressors(),
    )
    if name in VARIABLE_ATTRS:
        units, long_name = VARIABLE_ATTRS[name]
        arr.attrs.update({"units": units, "long_name": long_name})
    if data is not None:
        arr[...] = data
    return arr


RECON_KEYS = (
    "method",
    "gamma",
    "alpha",
    "step",
    "tol",
    "max_iter",
    "coherence_length_x_m",
    "coherence_length_y_m",
    "precision",
    "upsample",
    "field_upsample",
    "pad",
    "normalization",
    "preconditioner",
    "outlier_sigma",
    "angle_chain",  # stores made before session 18 lack it and resume with any chain length
    "diffuser_model",
    "diffuser_upstream_m",  # session 19, as angle_chain
    "single_material",  # session 33, as angle_chain
    "sample_field_grid",  # session 49, as angle_chain
    "sample_delta_over_beta",
)


def create_reconstruction(path: str | Path, info: ScanInfo, params: dict):
    """Create (or reopen, when its parameters and scan match) the reconstruction store.

    Returns the zarr group. A store made with other retrieval parameters, or from another
    scan (``params["scan_fingerprint"]``, :func:`pwf_dask.stores.integrity.scan_fingerprint`), is
    refused rather than mixed: resuming must never combine two reconstructions. A new store is
    built whole under a hidden name and renamed into place (:func:`integrity.atomic_directory`),
    so a kill during creation leaves no store at ``path``.
    """
    import zarr

    from pwf_dask.stores.integrity import atomic_directory

    path = str(path)
    if Path(path).exists():
        g = _reopen_reconstruction(path, info, params)
        if g is not None:
            return g
    with atomic_directory(path) as tmp:
        _build_reconstruction(str(tmp), info, params)
    return zarr.open_group(path, mode="r+", use_consolidated=False)


def _reopen_reconstruction(path: str, info: ScanInfo, params: dict):
    """The existing store at ``path`` if it is this reconstruction; None if it is an unfinished
    creation with nothing computed in it (removed, to be created again); else ScanError."""
    import shutil

    import zarr

    from pwf_dask.stores.integrity import Fingerprint

    try:
        g = zarr.open_group(path, mode="r+", use_consolidated=False)
    except Exception as exc:
        raise ScanError(f"{path}: exists and is not a reconstruction store ({type(exc).__name__})") from None
    if "pwf_dask_parameters" not in g.attrs:
        started = "iterations" in g and int(np.max(g["iterations"][...], initial=-1)) >= 0
        if "phase" in g and not started:  # a creation killed before its attributes (pre-#29 stores)
            shutil.rmtree(path)
            return None
        raise ScanError(f"{path}: exists and is not a complete reconstruction store; use a new path")
    old = json.loads(g.attrs["pwf_dask_parameters"])
    if "scan_fingerprint" in old and "scan_fingerprint" in params:
        diff = Fingerprint.decode(old["scan_fingerprint"]).differences(Fingerprint.decode(params["scan_fingerprint"]))
        if diff:
            raise ScanError(
                f"{path}: was made from another scan ({old.get('scan', g.attrs.get('scan'))}; its "
                f"{', '.join(diff)} differ); use a new path for this scan"
            )
    diff = [k for k in RECON_KEYS if k in old and k in params and str(old[k]) != str(params[k])]
    if diff:
        raise ScanError(
            f"{path}: exists with other parameters ({', '.join(diff)}); use a new path to reconstruct again"
        )
    npos, nang = info.n_positions, info.angles_deg.size
    if "phase" not in g or g["phase"].shape != (npos, nang, *info.shape):
        raise ScanError(f"{path}: exists and does not match this scan's shape")
    return g


def _build_reconstruction(path: str, info: ScanInfo, params: dict) -> None:
    """Every array and attribute of a new reconstruction store, written at ``path``."""
    import zarr

    npos, nang = info.n_positions, info.angles_deg.size
    ny, nx = info.shape
    g = zarr.open_group(path, mode="w")
    rb = row_block(ny, nx)
    create_variable(g, "position", (npos,), (npos,), ("position",), "int64", 0, np.arange(npos))
    create_variable(g, "angle", (nang,), (nang,), ("angle",), "float64", 0.0, info.angles_deg)
    create_variable(g, "y", (ny,), (ny,), ("y",), "float64", 0.0, info.y_m)
    create_variable(g, "x", (nx,), (nx,), ("x",), "float64", 0.0, info.x_m)
    for name in ("phase", "attenuation"):
        create_variable(
            g, name, (npos, nang, ny, nx), (1, 1, rb, nx), ("position", "angle", "y", "x"), "float32", np.nan
        )
    create_variable(g, "iterations", (npos, nang), (1, 1), ("position", "angle"), "int32", -1)
    create_variable(g, "converged", (npos, nang), (1, 1), ("position", "angle"), "bool", False)
    create_variable(g, "residual_rmse", (npos, nang), (1, 1), ("position", "angle"), "float32", np.nan)
    create_variable(g, "outlier_pixels", (npos, nang), (1, 1), ("position", "angle"), "int32", -1)
    # what each projection cost, kept with it: a run killed and resumed still has every timing
    create_variable(g, "retrieval_seconds", (npos, nang), (1, 1), ("position", "angle"), "float32", np.nan)
    # the fit's per-pixel residual is kept for one projection per position: what a user checks
    # first (structure in it is a model error), at the cost of one frame, not one per angle
    create_variable(g, "preview_residual", (npos, ny, nx), (1, rb, nx), ("position", "y", "x"), "float32", np.nan)
    # the speckle's measured drift (the multi-image trackers: the mean over the K positions)
    for name in ("diffuser_drift_y_px", "diffuser_drift_x_px"):
        create_variable(g, name, (npos, nang), (1, 1), ("position", "angle"), "float32", np.nan)
    # what the speckle could carry (calibration.sensitivity): below its limits the phase is unreliable
    for name in ("speckle_shift_over_grain", "speckle_visibility", "sample_misfit"):
        create_variable(g, name, (npos, nang), (1, 1), ("position", "angle"), "float32", np.nan)
    # what the background fit took from PWF's psi: a warm-started chain adds it back to start
    # from the solver's own psi (a tilt left out moves the whole speckle; workflow._start_psi)
    for name in ("background_plane_phase", "background_plane_attenuation"):
        create_variable(g, name, (npos, nang, 3), (1, 1, 3), ("position", "angle", "plane_term"), "float64", np.nan)
    attrs = {k: v for k, v in info.attrs.items() if isinstance(v, (int, float, str, bool))}
    attrs.update({k: v for k, v in params.items() if isinstance(v, (int, float, str, bool)) or v is None})
    attrs["pwf_dask_parameters"] = json.dumps(params, default=str)
    attrs["scan"] = info.path
    g.attrs.update(attrs)


def consolidate(path: str | Path) -> None:
    """Consolidate metadata so ``xarray.open_zarr`` opens the store in one read."""
    import zarr

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(str(path))


def create_scan(
    path: str | Path,
    *,
    n_positions: int,
    angles_deg,
    shape: tuple[int, int],
    pixel_size_m: float,
    dtype,
    attrs: dict,
    flat_dark: bool = False,
    x_m=None,
):
    """An empty scan store (docs/scan-format.md §1), one chunk per angle and whole frames; returns the group.
    Never over an existing path: a store or a folder of the user's files is not ours to clear."""
    import zarr

    if Path(path).exists():
        raise ValueError(f"{path} already exists; a new scan is written to a new path and never over one")
    ny, nx = shape
    nang = len(angles_deg)
    g = zarr.open_group(str(path), mode="w")
    x = x_m if x_m is not None else (np.arange(nx) - (nx - 1) / 2) * pixel_size_m
    y = (np.arange(ny) - (ny - 1) / 2) * pixel_size_m
    create_variable(g, "position", (n_positions,), (n_positions,), ("position",), "int64", 0, np.arange(n_positions))
    create_variable(g, "angle", (nang,), (nang,), ("angle",), "float64", 0.0, np.asarray(angles_deg, np.float64))
    create_variable(g, "y", (ny,), (ny,), ("y",), "float64", 0.0, y)
    create_variable(g, "x", (nx,), (nx,), ("x",), "float64", 0.0, np.asarray(x, np.float64))
    create_variable(
        g, "projections", (n_positions, nang, ny, nx), (1, 1, ny, nx), ("position", "angle", "y", "x"), dtype, 0
    )
    create_variable(g, "reference", (n_positions, ny, nx), (1, ny, nx), ("position", "y", "x"), dtype, 0)
    if flat_dark:
        for name in ("flat", "dark"):
            create_variable(g, name, (ny, nx), (ny, nx), ("y", "x"), dtype, 0)
    g.attrs.update(attrs)
    return g


def write_scan(
    path: str | Path,
    projections,
    reference,
    angles_deg,
    attrs: dict,
    *,
    flat=None,
    dark=None,
    pixel_size_m: float,
    x_m=None,
) -> None:
    """Write a whole scan store from in-memory arrays (small scans, tests)."""
    proj = np.asarray(projections)
    npos, _, ny, nx = proj.shape
    g = create_scan(
        path,
        n_positions=npos,
        angles_deg=angles_deg,
        shape=(ny, nx),
        pixel_size_m=pixel_size_m,
        dtype=proj.dtype,
        attrs=attrs,
        flat_dark=False,
        x_m=x_m,
    )
    g["projections"][...] = proj
    g["reference"][...] = np.asarray(reference)
    for name, a in (("flat", flat), ("dark", dark)):
        if a is not None:
            a = np.asarray(a)
            create_variable(g, name, a.shape, a.shape, ("y", "x"), a.dtype, 0, a)
    consolidate(path)
