"""Reconstructions out to the formats other tools read: float32 TIFF for Fiji, Avizo, napari.

:func:`export_tiff` writes the delta and beta tomograms of every diffuser position, one
ImageJ-flavoured multi-page TIFF per volume (pages along the rotation axis y, each a (v, u)
slice) or one file per slice. The voxel size rides in the TIFF resolution tags (pixels per
micrometre) and ImageJ's ``unit``/``spacing``, so Fiji shows micrometres and scale bars work.
Values are the store's float32 delta and beta, unscaled.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

EXPORT_LAYOUTS = ("stack", "slices")
EXPORT_VARIABLES = ("delta", "beta")


def _write(path: Path, data: np.ndarray, voxel_um: float, name: str) -> None:
    import tifffile

    tifffile.imwrite(
        path,
        np.ascontiguousarray(data, dtype=np.float32),
        imagej=True,
        resolution=(1.0 / voxel_um, 1.0 / voxel_um),
        metadata={"axes": "ZYX" if data.ndim == 3 else "YX", "unit": "um", "spacing": voxel_um, "Info": name},
    )


def export_tiff(
    recon_path: str | Path,
    out_dir: str | Path,
    *,
    layout: str = "stack",
    variables: tuple[str, ...] = EXPORT_VARIABLES,
) -> list[Path]:
    """Write each position's ``variables`` as float32 TIFF into ``out_dir`` (created; files
    there of the same names are refused, never overwritten). ``layout`` "stack": one file per
    volume, ``delta_position0.tif``; "slices": a folder per volume of ``y0000.tif`` ... .
    Returns the files written."""
    import xarray as xr

    if layout not in EXPORT_LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}: use {' or '.join(EXPORT_LAYOUTS)}")
    ds = xr.open_zarr(str(recon_path))
    for name in variables:
        if name not in ds:
            raise ValueError(f"{recon_path}: no {name} tomogram to export (run `pwf-dask tomo` first)")
    if "tomo_done" in ds and int(ds["tomo_done"].values.min()) == 0:
        raise ValueError(f"{recon_path}: the tomograms are not complete (run `pwf-dask tomo` to finish them)")
    voxel_um = float(ds.attrs["pixel_size_m"]) * 1e6
    out = Path(out_dir)
    targets = [
        (name, p, out / (f"{name}_position{p}.tif" if layout == "stack" else f"{name}_position{p}"))
        for name in variables
        for p in range(ds.sizes["position"])
    ]
    clash = [str(t) for _, _, t in targets if t.exists()]
    if clash:
        raise ValueError(f"{clash[0]} already exists; export writes new files and never over old ones")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, p, target in targets:
        volume = ds[name][p]  # (y, v, u), read a slice at a time for the per-slice layout
        label = f"{name} (refractive index), position {p}, from {recon_path}"
        if layout == "stack":
            _write(target, volume.values, voxel_um, label)
            written.append(target)
            continue
        target.mkdir()
        for j in range(volume.sizes["y"]):
            f = target / f"y{j:04d}.tif"
            _write(f, volume[j].values, voxel_um, label)
            written.append(f)
    return written
