"""Store integrity: checksummed chunks, chunk checks, atomic creation, a scan fingerprint.

A reconstruction store is trusted chunk by chunk, never as a whole:

* every chunk is written with zstd's content checksum (:data:`CHUNK_COMPRESSORS`), so a
  flipped byte fails to decode instead of reading as 3.4e38;
* a projection counts as done only when its bookkeeping says so *and* all its ``phase`` and
  ``attenuation`` chunks are there (:func:`missing_projection_chunks`); a tomography row block
  likewise (:func:`missing_block_chunks`);
* a chunk that is missing, truncated, garbage or fails its checksum is named (array, chunk
  index, projection) by :class:`DamagedChunk`, removed, and its projection or row block is
  marked not done (:func:`reset_projection`, :func:`reset_block`), so the next run recomputes it;
* a store is created under a hidden sibling name and renamed into place when whole
  (:func:`atomic_directory`): a store at the user's path is always complete;
* :func:`scan_fingerprint` digests what makes a scan that scan (shapes, angles, geometry,
  reference, flat and dark), so a resume against another scan is refused.

Stores are directories on a (shared) filesystem: pwf-dask's chunk keys are the zarr v3 default
``NAME/c/i/j/...``. A scan written by another tool (zarr v2, other key encodings, sharding,
chunks left out where they equal the fill value) is read as zarr reads it: only pwf-dask's
own, checksummed arrays must hold every chunk (:func:`stores_every_chunk`).
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zarr

# every chunk written is stored, even one equal to the fill value (a dark frame of zeros): a
# missing chunk then always means a lost one, which is what the checks here rely on
zarr.config.set({"array.write_empty_chunks": True})


def chunk_compressors() -> list:
    """zstd with its content checksum: zarr 3's default codec plus the check (issue #29)."""
    from zarr.codecs import ZstdCodec

    return [ZstdCodec(level=0, checksum=True)]


class DamagedChunk(RuntimeError):
    """A chunk that is missing where it must exist, or cannot be decoded; one line naming it."""

    def __init__(self, store: str, name: str, index: tuple[int, ...], problem: str):
        self.store, self.name, self.index, self.problem = store, name, tuple(int(i) for i in index), problem
        super().__init__(f"{store}: {name} chunk {self.index} is {problem}")


def chunk_path(store: str | Path, name: str, index: tuple[int, ...], arr=None) -> Path:
    """The file of chunk ``index``: the zarr v3 default key of pwf-dask's arrays, or ``arr``'s
    own key encoding where it is given (zarr v2's ``i.j``, a v3 array with ``.`` separators)."""
    if arr is not None:
        return Path(store, name, arr.metadata.encode_chunk_key(tuple(int(i) for i in index)))
    return Path(store, name, "c", *(str(int(i)) for i in index))


def has_checksums(arr) -> bool:
    """Whether ``arr``'s chunks carry a checksum (stores made before issue #29 do not)."""
    for codec in getattr(arr.metadata, "codecs", ()):
        if getattr(codec, "checksum", False) or type(codec).__name__ == "Crc32cCodec":
            return True
    return False


def stores_every_chunk(arr) -> bool:
    """Whether a missing chunk of ``arr`` is a lost one: pwf-dask writes every chunk of its
    (checksummed) arrays; another writer may leave out a chunk equal to the fill value, which
    zarr then reads as that value."""
    return has_checksums(arr)


def read_chunk(store: str | Path, arr, name: str, index: tuple[int, ...]) -> np.ndarray:
    """One chunk, decoded and verified; raises :class:`DamagedChunk` naming it."""
    if stores_every_chunk(arr) and not chunk_path(store, name, index, arr).exists():
        raise DamagedChunk(str(store), name, index, "missing")
    try:
        return np.asarray(arr.blocks[tuple(index)])
    except Exception as exc:  # zstd raises RuntimeError, numcodecs ValueError, reshape errors ...
        raise DamagedChunk(str(store), name, index, f"unreadable ({_short(exc)})") from None


def _short(exc: Exception) -> str:
    return str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__


def chunk_grid(arr) -> Iterator[tuple[int, ...]]:
    return itertools.product(*(range(-(-s // c)) for s, c in zip(arr.shape, arr.chunks)))


def selected_chunks(arr, selection) -> Iterator[tuple[int, ...]]:
    """The chunk indices that a basic selection (ints, slices with step 1, ``...``) touches."""
    sel = selection if isinstance(selection, tuple) else (selection,)
    if any(s is Ellipsis for s in sel):
        i = sel.index(Ellipsis)
        sel = sel[:i] + (slice(None),) * (arr.ndim - len(sel) + 1) + sel[i + 1 :]
    sel = sel + (slice(None),) * (arr.ndim - len(sel))
    ranges = []
    for s, n, c in zip(sel, arr.shape, arr.chunks):
        if isinstance(s, slice):
            start, stop, _ = s.indices(n)
            ranges.append(range(start // c, max(start, stop - 1) // c + 1) if stop > start else range(0))
        else:
            ranges.append(range(int(s) % n // c, int(s) % n // c + 1))
    return itertools.product(*ranges)


def read_checked(store: str | Path, arr, name: str, selection=...) -> np.ndarray:
    """``arr[selection]``, refusing to read a missing chunk as its fill value or a damaged one
    as data: raises :class:`DamagedChunk` naming the first such chunk of the selection."""
    chunks = list(selected_chunks(arr, selection))
    for index in chunks if stores_every_chunk(arr) else ():
        if not chunk_path(store, name, index, arr).exists():
            raise DamagedChunk(str(store), name, index, "missing")
    try:
        return arr[selection]
    except Exception:
        for index in chunks:
            read_chunk(store, arr, name, index)
        raise


def store_root(group) -> str:
    """The directory of a group opened from a local path."""
    return str(group.store.root)


def read_bookkeeping(store: str | Path, group, name: str) -> tuple[np.ndarray, list[DamagedChunk]]:
    """A bookkeeping array (``iterations``, ``tomo_done``: one element per chunk) with any
    unreadable chunk removed, so that it reads as its fill value (not done)."""
    arr = group[name]
    try:
        return arr[...], []
    except Exception:
        damaged = []
        for index in chunk_grid(arr):
            if not chunk_path(store, name, index).exists():
                continue
            try:
                read_chunk(store, arr, name, index)
            except DamagedChunk as exc:
                damaged.append(exc)
                chunk_path(store, name, index).unlink()
        return arr[...], damaged


def projection_chunks(group, p: int, a: int) -> list[tuple[str, tuple[int, ...]]]:
    """The (array, chunk index) pairs that hold projection (p, a)'s phase and attenuation."""
    out = []
    for name in ("phase", "attenuation"):
        arr = group[name]
        nblocks = -(-arr.shape[2] // arr.chunks[2])
        out += [(name, (p, a, b, 0)) for b in range(nblocks)]
    return out


def missing_projection_chunks(store: str | Path, group, done: np.ndarray) -> dict[tuple[int, int], list]:
    """Projections marked done whose phase/attenuation chunks are not all there (one stat each)."""
    missing: dict[tuple[int, int], list] = {}
    for p, a in zip(*np.nonzero(done >= 0)):
        lost = [(n, i) for n, i in projection_chunks(group, int(p), int(a)) if not chunk_path(store, n, i).exists()]
        if lost:
            missing[(int(p), int(a))] = lost
    return missing


def reset_projection(store: str | Path, group, p: int, a: int, remove: bool = True) -> None:
    """Mark projection (p, a) not done (its bookkeeping first, then its damaged data)."""
    group["iterations"][p, a] = np.int32(-1)
    if remove:
        for name, index in projection_chunks(group, p, a):
            with contextlib.suppress(FileNotFoundError):
                chunk_path(store, name, index).unlink()


def block_chunks(p: int, b: int) -> list[tuple[str, tuple[int, ...]]]:
    return [(name, (p, b, 0, 0)) for name in ("delta", "beta")]


def missing_block_chunks(store: str | Path, done: np.ndarray) -> list[tuple[int, int]]:
    """Row blocks marked done whose delta/beta chunks are not both there."""
    return [
        (int(p), int(b))
        for p, b in zip(*np.nonzero(done >= 1))
        if not all(chunk_path(store, n, i).exists() for n, i in block_chunks(int(p), int(b)))
    ]


def reset_block(store: str | Path, group, p: int, b: int) -> None:
    group["tomo_done"][p, b] = np.int8(0)
    for name, index in block_chunks(p, b):
        with contextlib.suppress(FileNotFoundError):
            chunk_path(store, name, index).unlink()


# --- atomic creation ------------------------------------------------------------------------


def partial_path(path: str | Path) -> Path:
    """Where a store is built before it is renamed into place (a hidden sibling: same filesystem)."""
    p = Path(path)
    return p.with_name(f".{p.name}.partial")


@contextlib.contextmanager
def atomic_directory(path: str | Path) -> Iterator[Path]:
    """Build a directory under :func:`partial_path` and rename it to ``path`` when the block
    ends without error. A leftover of a killed creation (ours, by its name) is cleared first;
    on an error the partial directory is removed and ``path`` never appears."""
    final, tmp = Path(path), partial_path(path)
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    os.replace(tmp, final)


# --- scan fingerprint -------------------------------------------------------------------------

#: the scan attributes a reconstruction depends on
FINGERPRINT_ATTRS = (
    "energy_eV",
    "pixel_size_m",
    "sample_diffuser_distance_m",
    "diffuser_detector_distance_m",
    "diffuser_upstream_m",
    "coherence_length_x_m",
    "coherence_length_y_m",
    "flat_dark_corrected",
)


@dataclass
class Fingerprint:
    """Digests of the parts of a scan, so that a refusal can say which part differs."""

    parts: dict[str, str] = field(default_factory=dict)

    def encode(self) -> str:
        import json

        return json.dumps(self.parts, sort_keys=True)

    @classmethod
    def decode(cls, text: str) -> Fingerprint:
        import json

        return cls(json.loads(text))

    def differences(self, other: Fingerprint) -> list[str]:
        return [k for k in sorted(set(self.parts) | set(other.parts)) if self.parts.get(k) != other.parts.get(k)]


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def scan_fingerprint(scan_group) -> Fingerprint:
    """Shapes, angles, geometry, and the reference, flat and dark frames of a scan store
    (one read of the references: a few frames, not the projections)."""
    g = scan_group
    geometry = {k: g.attrs[k] for k in FINGERPRINT_ATTRS if k in g.attrs}
    parts = {
        "shape": _digest(np.asarray(g["projections"].shape)),
        "angles": _digest(g["angle"][...]),
        "geometry": hashlib.sha256(repr(sorted(geometry.items())).encode()).hexdigest()[:16],
        "reference": _digest(g["reference"][...]),
    }
    for name in ("flat", "dark"):
        parts[name] = _digest(g[name][...]) if name in g else "none"
    return Fingerprint(parts)


# --- verify -----------------------------------------------------------------------------------

#: arrays whose chunks exist only for what is done: (bookkeeping array, how a chunk maps to it)
_DONE_BY = {
    "phase": ("iterations", lambda i: i[:2], 0),
    "attenuation": ("iterations", lambda i: i[:2], 0),
    "delta": ("tomo_done", lambda i: i[:2], 1),
    "beta": ("tomo_done", lambda i: i[:2], 1),
}
#: arrays written only for some entries, or only in some runs: a missing chunk is no fault
_OPTIONAL = (
    "iterations",
    "tomo_done",
    "converged",
    "residual_rmse",
    "outlier_pixels",
    "retrieval_seconds",
    "preview_residual",
    "diffuser",  # a missing or damaged fit is made again by the next run
    "diffuser_drift_y_px",
    "diffuser_drift_x_px",
    "speckle_shift_over_grain",
    "speckle_visibility",
    "sample_misfit",
    "position_disagreement",
    "background_plane_phase",
    "background_plane_attenuation",
)


@dataclass
class Verification:
    """What :func:`verify_store` found: per array, chunks read, and the faults by name."""

    path: str
    checked: dict[str, int] = field(default_factory=dict)
    faults: list[DamagedChunk] = field(default_factory=list)
    unchecksummed: list[str] = field(default_factory=list)
    repaired: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.faults

    def lines(self) -> list[str]:
        out = [f"{self.path}: {sum(self.checked.values())} chunks of {len(self.checked)} arrays read"]
        out += [f"  {f.name} chunk {f.index}: {f.problem}" for f in self.faults]
        if self.unchecksummed:
            names = ", ".join(self.unchecksummed)
            out.append(f"  no checksums (written by another tool, or by pwf-dask before issue #29): {names}")
        out += [f"  repaired: {r}" for r in self.repaired]
        out.append("  intact" if self.ok else f"  {len(self.faults)} damaged or missing chunks")
        return out


def _expected(arr, name: str, index: tuple[int, ...], done: dict) -> bool:
    """Whether a chunk must exist. Only pwf-dask's own (checksummed) arrays store every chunk;
    another writer may leave out a chunk equal to the fill value."""
    if name in _OPTIONAL or not stores_every_chunk(arr):
        return False
    if name in _DONE_BY:
        book, key, threshold = _DONE_BY[name]
        return book in done and bool(done[book][key(index)] >= threshold)
    return True  # coordinates, scan frames, FSC curves: written whole


def verify_store(path: str | Path, repair: bool = False) -> Verification:
    """Read every chunk of a scan or reconstruction store: a chunk that should exist (all of a
    scan's; a reconstruction's coordinates, and the data of what its bookkeeping marks done) and
    is missing, or that fails to decode (checksum, truncation, garbage), is a fault.

    ``repair``: faults in a reconstruction's projections or row blocks are removed and marked
    not done (the next ``run`` recomputes them); other faults cannot be repaired here.
    """
    import zarr

    path = str(path)
    group = zarr.open_group(path, mode="r+" if repair else "r", use_consolidated=False)
    report = Verification(path)
    done = {}
    for book in ("iterations", "tomo_done"):
        if book in group:
            done[book], bad = read_bookkeeping(path, group, book) if repair else (_read_or_fill(path, group, book))
            report.faults += bad
    for name, arr in sorted(group.arrays()):
        if not has_checksums(arr):
            report.unchecksummed.append(name)
        report.checked[name] = 0
        for index in chunk_grid(arr):
            exists = chunk_path(path, name, index, arr).exists()
            if not exists and not _expected(arr, name, index, done):
                continue
            report.checked[name] += 1
            try:
                read_chunk(path, arr, name, index)
            except DamagedChunk as exc:
                report.faults.append(exc)
    if repair:
        _repair(path, group, report)
    return report


def _read_or_fill(path, group, book) -> tuple[np.ndarray, list]:
    """A bookkeeping array read without changing the store: damaged chunks read as not done."""
    arr = group[book]
    try:
        return arr[...], []
    except Exception:
        values = np.full(arr.shape, arr.fill_value, dtype=arr.dtype)
        bad = []
        for index in chunk_grid(arr):
            if chunk_path(path, book, index).exists():
                try:
                    values[index] = read_chunk(path, arr, book, index).reshape(())
                except DamagedChunk as exc:
                    bad.append(exc)
        return values, bad


def _repair(path: str, group, report: Verification) -> None:
    for fault in report.faults:
        if fault.name in ("phase", "attenuation"):
            reset_projection(path, group, *fault.index[:2])
            report.repaired.append(f"projection {fault.index[:2]} marked not done")
        elif fault.name in ("delta", "beta"):
            reset_block(path, group, *fault.index[:2])
            report.repaired.append(f"row block {fault.index[:2]} marked not done")
        elif fault.name == "diffuser":
            with contextlib.suppress(FileNotFoundError):
                chunk_path(path, fault.name, fault.index).unlink()
            report.repaired.append(f"diffuser of position {fault.index[0]} removed (fitted again by the next run)")
        elif fault.name in ("iterations", "tomo_done"):
            report.repaired.append(f"{fault.name} {fault.index} removed (not done)")
    report.repaired = list(dict.fromkeys(report.repaired))
