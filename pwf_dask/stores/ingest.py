"""Detector files into a scan store (docs/scan-format.md §1): TIFF images and HDF5 datasets.

Beamlines write speckle scans as TIFF files (one per angle, or multi-page stacks) or as HDF5
(the DXchange layout of tomopy: ``/exchange/data``, ``data_white``, ``data_dark``, ``theta``).
:func:`ingest_scan` streams them, one frame at a time, into the chunked Zarr scan that every
stage reads. A frame source is named by one string:

* a file or glob pattern of TIFF files (``"proj_*.tif"``), sorted in natural order
  (``proj_2`` before ``proj_10``); every page of every file is one frame;
* ``"FILE.h5:/path/to/dataset"``, an HDF5 dataset of shape (frames, y, x) or (y, x); for the
  projections also (position, angle, y, x).

Reference, flat and dark sources with several frames are averaged (the usual series of flats
and darks; a longer reference exposure lowers the noise PWF fits against). Counts stay
uint16 when every source is uint16; averages are then rounded to whole counts (a relative
error below 0.5 / counts, far below the photon noise). A store that already exists is never
touched, and one that fails while being written is removed, so nothing is half written.
"""

from __future__ import annotations

import glob
import re
import shutil
import warnings
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pwf_dask.progress import Progress
from pwf_dask.stores.scan_io import FULL_SCALE_ATTR, ScanError, consolidate, correct, create_scan, create_variable

#: The DXchange layout (tomopy, dxchange): the defaults for an HDF5 file given alone.
DXCHANGE = {
    "projections": "/exchange/data",
    "reference": "/exchange/data_white",
    "dark": "/exchange/data_dark",
    "angles": "/exchange/theta",
}


def _natural_key(path: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path)]


def _split_hdf5(spec: str) -> tuple[str, str] | None:
    """("FILE.h5", "/dataset") for an HDF5 spec, None for a TIFF pattern."""
    m = re.match(r"^(.*\.(?:h5|hdf5|hdf|nxs)):(/.*)$", spec, flags=re.IGNORECASE)
    return (m.group(1), m.group(2)) if m else None


class FrameSource:
    """Frames of one spec, read lazily: ``len``, ``frame_shape``, ``dtype``, ``frame(i)``.

    For an HDF5 projections dataset of 4 dims, ``positions`` > 1 and ``frame(i, k)`` reads
    angle i of position k.
    """

    def __init__(self, spec: str, what: str):
        self.spec, self.what = spec, what
        self._file = None
        self._tiff: list[tuple[str, int]] | None = None
        # open TIFF files, their parsed pages cached: a page is found by walking the file's
        # chain of image directories, so reopening per frame costs O(n^2) on an 801-page stack
        self._open_tiffs: dict = {}
        h5 = _split_hdf5(spec)
        if h5 is not None:
            self._open_hdf5(*h5)
        else:
            self._open_tiff(spec)

    def _open_hdf5(self, filename: str, dataset: str) -> None:
        import h5py

        try:  # detector files are often compressed with filter plugins (bitshuffle, LZ4)
            import hdf5plugin  # noqa: F401
        except ImportError:
            pass

        if not Path(filename).is_file():
            raise ScanError(f"{self.what}: no such HDF5 file {filename}")
        f = h5py.File(filename, "r")
        if dataset not in f or not isinstance(f[dataset], h5py.Dataset):
            f.close()
            raise ScanError(f"{self.what}: {filename} has no dataset {dataset}")
        d = f[dataset]
        self._file, self._data = f, d
        if d.ndim == 2:
            self.positions, self._n, self.frame_shape = 1, 1, tuple(d.shape)
            self._index = lambda i, k: (slice(None), slice(None))
        elif d.ndim == 3:
            self.positions, self._n, self.frame_shape = 1, d.shape[0], tuple(d.shape[1:])
            self._index = lambda i, k: (i,)
        elif d.ndim == 4:
            self.positions, self._n, self.frame_shape = d.shape[0], d.shape[1], tuple(d.shape[2:])
            self._index = lambda i, k: (k, i)
        else:
            f.close()
            raise ScanError(f"{self.what}: {self.spec} has {d.ndim} dims, expected (frames, y, x) or (y, x)")
        self.dtype = np.dtype(d.dtype)

    def _open_tiff(self, pattern: str) -> None:
        import tifffile

        files = sorted(glob.glob(pattern), key=_natural_key) if glob.has_magic(pattern) else [pattern]
        files = [f for f in files if Path(f).is_file()]
        if not files:
            raise ScanError(f"{self.what}: no file matches {pattern}")
        pages: list[tuple[str, int]] = []
        shape = dtype = None
        for name in files:
            try:
                with tifffile.TiffFile(name) as tif:
                    for j, page in enumerate(tif.pages):
                        if shape is None:
                            shape, dtype = tuple(page.shape), np.dtype(page.dtype)
                        elif tuple(page.shape) != shape:
                            raise ScanError(f"{self.what}: {name} page {j} is {tuple(page.shape)}, not {shape}")
                        pages.append((name, j))
            except tifffile.TiffFileError as exc:
                raise ScanError(f"{self.what}: {name} is not a readable TIFF ({exc})") from None
        if len(shape) != 2:
            raise ScanError(f"{self.what}: {files[0]} has frames of shape {shape}, expected 2-D images")
        self._tiff, self.positions, self._n = pages, 1, len(pages)
        self.frame_shape, self.dtype = shape, dtype

    def __len__(self) -> int:
        return self._n

    def frame(self, i: int, position: int = 0) -> np.ndarray:
        if self._tiff is not None:
            import tifffile

            name, page = self._tiff[i]
            tif = self._open_tiffs.get(name)
            if tif is None:
                tif = self._open_tiffs[name] = tifffile.TiffFile(name)
                tif.pages.cache = True
            return tif.pages[page].asarray()
        return np.asarray(self._data[self._index(i, position)])

    def mean(self, position: int = 0) -> np.ndarray:
        """The average of all frames (of one position), in float64."""
        acc = np.zeros(self.frame_shape, np.float64)
        for i in range(len(self)):
            acc += self.frame(i, position)
        return acc / len(self)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        for tif in self._open_tiffs.values():
            tif.close()


def read_angles_deg(spec: str | None, n: int, start_stop: Sequence[float] | None, unit: str = "deg") -> np.ndarray:
    """Rotation angles in degrees: from ``"FILE.h5:/theta"``, a text file (one per line or
    whitespace separated), or ``start_stop`` (n angles from start to stop inclusive)."""
    if unit not in ("deg", "rad"):
        raise ScanError(f"angles unit must be 'deg' or 'rad', not {unit!r}")
    if (spec is None) == (start_stop is None):
        raise ScanError("angles: give either a start and stop or a file of angles, not both or neither")
    if start_stop is not None:
        a = np.linspace(float(start_stop[0]), float(start_stop[1]), n)
    else:
        h5 = _split_hdf5(spec)
        if h5 is not None:
            import h5py

            if not Path(h5[0]).is_file():
                raise ScanError(f"angles: no such HDF5 file {h5[0]}")
            with h5py.File(h5[0], "r") as f:
                if h5[1] not in f:
                    raise ScanError(f"angles: {h5[0]} has no dataset {h5[1]}")
                a = np.asarray(f[h5[1]], np.float64).ravel()
        else:
            if not Path(spec).is_file():
                raise ScanError(f"angles: no such file {spec}")
            try:
                a = np.loadtxt(spec, dtype=np.float64, ndmin=1).ravel()
            except ValueError as exc:
                raise ScanError(f"angles: {spec} is not a list of numbers ({exc})") from None
        if a.size != n:
            raise ScanError(f"angles: {spec} has {a.size} angles for {n} projections")
    if not np.all(np.isfinite(a)):
        raise ScanError("angles: non-finite values")
    return np.rad2deg(a) if unit == "rad" else a


@dataclass
class _Sources:
    """The frame sources of one ingest, opened, and where each frame of the store comes from."""

    #: per diffuser position: its projections source and its index in a 4-D HDF5 dataset
    positions: list[tuple[FrameSource, int]]
    #: per diffuser position: the reference source, the frame or position in it, averaged or not
    references: list[tuple[FrameSource, int, bool]]
    flat: FrameSource | None
    dark: FrameSource | None
    opened: list[FrameSource]

    @property
    def shape(self) -> tuple[int, int]:
        return self.positions[0][0].frame_shape

    @property
    def n_angles(self) -> int:
        return len(self.positions[0][0])

    def close(self) -> None:
        for s in self.opened:
            s.close()


def _open_sources(proj_specs: list[str], ref_specs: list[str], flat: str | None, dark: str | None) -> _Sources:
    """Open every source and check that they fit together: one reference per position, equal
    angle counts and one frame shape; all are closed again on a refusal."""
    opened: list[FrameSource] = []
    try:
        proj = [FrameSource(s, "projections") for s in proj_specs]
        opened += proj
        refs = [FrameSource(s, "reference") for s in ref_specs]
        opened += refs
        flat_src = FrameSource(flat, "flat") if flat else None
        dark_src = FrameSource(dark, "dark") if dark else None
        opened += [s for s in (flat_src, dark_src) if s is not None]
        if len(proj) == 1 and proj[0].positions > 1:
            positions = [(proj[0], k) for k in range(proj[0].positions)]
        else:
            positions = [(p, 0) for p in proj]
        k_total = len(positions)
        if any(len(src) != len(positions[0][0]) for src, _ in positions):
            raise ScanError(f"projections: positions have {[len(s) for s, _ in positions]} frames, expected equal")
        if len(refs) == 1 and refs[0].positions == 1 and k_total > 1 and len(refs[0]) == k_total:
            references = [(refs[0], k, False) for k in range(k_total)]  # one frame per position
        elif len(refs) == k_total:
            references = [(r, 0, True) for r in refs]  # each averaged
        else:
            raise ScanError(f"reference: {len(refs)} sources for {k_total} diffuser positions")
        sources = _Sources(positions, references, flat_src, dark_src, opened)
        for s in opened:
            if s.frame_shape != sources.shape:
                raise ScanError(f"{s.what}: frames of {s.spec} are {s.frame_shape}, projections are {sources.shape}")
        if sources.n_angles < 1:
            raise ScanError("projections: no frames")
        return sources
    except BaseException:
        for s in opened:
            s.close()
        raise


def _full_scale_counts(sources: _Sources, given: float | None, flat_dark_corrected: bool) -> float | None:
    """The raw counts at which the detector saturates: as given (checked before the sources
    are opened), else the sources' common integer type maximum; None for corrected or
    floating-point sources."""
    if given is not None:
        return float(given)
    kinds = {np.dtype(s.dtype) for s in sources.opened}
    if flat_dark_corrected or len(kinds) != 1 or next(iter(kinds)).kind not in "ui":
        return None
    return float(np.iinfo(next(iter(kinds))).max)


def _scan_attrs(geometry, *, flat_dark_corrected: bool, coherence: tuple, specs: dict) -> dict:
    """The scan store's root attributes (docs/scan-format.md §1) and the ingest's sources."""
    attrs = {
        "energy_eV": geometry.energy_eV,
        "pixel_size_m": geometry.pixel_size_m,
        "sample_diffuser_distance_m": geometry.sample_diffuser_distance_m,
        "diffuser_detector_distance_m": geometry.diffuser_detector_distance_m,
        "flat_dark_corrected": bool(flat_dark_corrected),
        **({"diffuser_upstream_m": geometry.diffuser_upstream_m} if geometry.diffuser_upstream_m else {}),
        "ingest_sources": specs,
    }
    cx, cy = coherence
    if cx is not None or cy is not None:
        if cx is None or cy is None:
            raise ScanError("give both coherence lengths (x and y) or neither")
        attrs["coherence_length_x_m"], attrs["coherence_length_y_m"] = float(cx), float(cy)
    return attrs


@dataclass
class _FrameStorage:
    """How an ingest stores its frames: uint16 counts stay integers (rounded, clipped), all else
    float32; each frame is checked after the flat/dark correction it will get."""

    integer: bool
    flat_dark_corrected: bool
    flat: np.ndarray | None = None
    dark: np.ndarray | None = None

    @property
    def dtype(self):
        return np.uint16 if self.integer else np.float32

    def stored(self, a) -> np.ndarray:
        return np.clip(np.rint(a), 0, 65535).astype(np.uint16) if self.integer else np.asarray(a, np.float32)

    def check(self, name: str, img) -> None:
        a = correct(img, self.flat, self.dark, self.flat_dark_corrected)
        if not np.all(np.isfinite(a)):
            raise ScanError(f"{name}: non-finite values after flat/dark correction")
        if np.any(a < 0):
            raise ScanError(f"{name}: negative values after flat/dark correction (min {float(a.min()):.3g})")


def _frame_storage(sources: _Sources, flat_dark_corrected: bool) -> _FrameStorage:
    """The storage of these sources' frames, with the flat and dark (each averaged) it checks them by."""
    integer = all(s.dtype == np.uint16 for s in sources.opened) and not flat_dark_corrected
    if not (flat_dark_corrected or sources.flat or sources.dark):
        warnings.warn(
            "no flat and no dark: the frames are used as they are (a dark offset then reads as attenuation; "
            "give --flat/--dark, or --flat-dark-corrected if they already are)",
            UserWarning,
            stacklevel=3,
        )
    storage = _FrameStorage(integer, flat_dark_corrected)
    storage.flat = storage.stored(sources.flat.mean()) if sources.flat else None
    storage.dark = storage.stored(sources.dark.mean()) if sources.dark else None
    if storage.flat is not None and storage.dark is not None:
        dead = storage.flat.astype(np.float32) <= storage.dark
        if dead.any():
            (row, col), n = np.argwhere(dead)[0], int(dead.sum())
            raise ScanError(
                f"flat: {n} pixel{'s are' if n > 1 else ' is'} not above the dark (flat - dark <= 0), the first at "
                f"row {row}, column {col}: their corrected intensity would be infinite; check that --flat and --dark "
                "are not swapped, or replace those pixels"
            )
    return storage


def _write_frames(g, sources: _Sources, storage: _FrameStorage, progress: bool) -> None:
    """The flat and dark, every reference, then every projection, each checked as it is written."""
    shape = sources.shape
    for name, img in (("flat", storage.flat), ("dark", storage.dark)):
        if img is not None:
            create_variable(g, name, shape, shape, ("y", "x"), storage.dtype, 0, img)
    for k, (src, idx, average) in enumerate(sources.references):
        img = storage.stored(src.mean(idx) if average else src.frame(k))
        storage.check(f"reference {k}", img)
        g["reference"][k] = img
    done = [0]
    total = len(sources.positions) * sources.n_angles
    with Progress("ingest", total, lambda: done[0], unit="projections") if progress else nullcontext():
        for k, (src, idx) in enumerate(sources.positions):
            for i in range(sources.n_angles):
                img = storage.stored(src.frame(i, idx))
                storage.check(f"projection {i} of position {k} ({src.spec})", img)
                g["projections"][k, i] = img
                done[0] += 1


def ingest_scan(
    out: str | Path,
    *,
    projections: Sequence[str] | str,
    reference: Sequence[str] | str,
    energy_eV: float,
    pixel_size_m: float,
    sample_diffuser_distance_m: float,
    diffuser_detector_distance_m: float,
    flat: str | None = None,
    dark: str | None = None,
    angles: str | None = None,
    angles_range_deg: Sequence[float] | None = None,
    angles_unit: str = "deg",
    coherence_length_x_m: float | None = None,
    coherence_length_y_m: float | None = None,
    flat_dark_corrected: bool = False,
    diffuser_upstream_m: float = 0.0,
    full_scale_counts: float | None = None,
    progress: bool = True,
) -> str:
    """Write a docs/scan-format.md §1 scan store at ``out`` from TIFF/HDF5 frame sources; returns its path.

    ``projections`` and ``reference``: one spec each per diffuser position (K >= 1), or one
    HDF5 projections dataset of 4 dims (position, angle, y, x) with a reference of K frames.
    ``angles`` (a file or HDF5 spec) or ``angles_range_deg`` (start, stop; inclusive) give the
    rotation angles. Every frame is checked as it is written (finite, and non-negative after
    flat/dark correction), so a bad scan fails here with the frame named, and the partial
    store is removed. ``diffuser_upstream_m`` > 0 records a diffuser that far upstream of the
    sample (with ``sample_diffuser_distance_m`` = 0; not in docs/scan-format.md §1, read by PWF).
    ``full_scale_counts``: the raw counts at which the detector saturates (4095 for a 12-bit
    camera), recorded so that PWF leaves such pixels out of its fit; by default the sources'
    integer type maximum (255 for uint8 frames, stored as float32), none for float sources.
    """
    from pwf_dask.physics.geometry import Geometry
    from pwf_dask.physics.optics import check_plausible_geometry

    out = Path(out)
    if out.exists():
        raise ScanError(f"{out} already exists; ingest writes a new store and never overwrites one")
    try:
        geometry = Geometry(
            energy_eV, pixel_size_m, sample_diffuser_distance_m, diffuser_detector_distance_m, diffuser_upstream_m
        )
        check_plausible_geometry(coherence_length_x_m=coherence_length_x_m, coherence_length_y_m=coherence_length_y_m)
    except ValueError as exc:
        raise ScanError(str(exc)) from None
    if full_scale_counts is not None and not (np.isfinite(full_scale_counts) and full_scale_counts > 0):
        raise ScanError(f"full_scale_counts must be a positive number of counts, got {full_scale_counts}")
    proj_specs = [projections] if isinstance(projections, str) else list(projections)
    ref_specs = [reference] if isinstance(reference, str) else list(reference)
    sources = _open_sources(proj_specs, ref_specs, flat, dark)
    try:
        angles_deg = read_angles_deg(angles, sources.n_angles, angles_range_deg, angles_unit)
        storage = _frame_storage(sources, flat_dark_corrected)
        specs = {
            "projections": proj_specs,
            "reference": ref_specs,
            "flat": flat,
            "dark": dark,
            "angles": angles or list(angles_range_deg),
        }
        coherence = (coherence_length_x_m, coherence_length_y_m)
        attrs = _scan_attrs(geometry, flat_dark_corrected=flat_dark_corrected, coherence=coherence, specs=specs)
        full_scale = _full_scale_counts(sources, full_scale_counts, flat_dark_corrected)
        if full_scale is not None:
            attrs[FULL_SCALE_ATTR] = full_scale
    except BaseException:
        sources.close()
        raise
    try:
        g = create_scan(
            out,
            n_positions=len(sources.positions),
            angles_deg=angles_deg,
            shape=sources.shape,
            pixel_size_m=geometry.pixel_size_m,
            dtype=storage.dtype,
            attrs=attrs,
            flat_dark=False,
        )
        _write_frames(g, sources, storage, progress)
        consolidate(out)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    finally:
        sources.close()
    return str(out)


def dxchange_specs(filename: str) -> dict[str, str]:
    """Source specs of the DXchange datasets present in ``filename`` (tomopy's layout: the
    sample frames, ``data_white`` as the diffuser reference, ``data_dark``, ``theta`` in
    degrees); keys projections, reference, dark, angles."""
    import h5py

    if not Path(filename).is_file():
        raise ScanError(f"--dxchange: no such HDF5 file {filename}")
    with h5py.File(filename, "r") as f:
        found = {key: f"{filename}:{path}" for key, path in DXCHANGE.items() if path in f}
    for key in ("projections", "reference"):
        if key not in found:
            raise ScanError(f"--dxchange: {filename} has no {DXCHANGE[key]}")
    return found
