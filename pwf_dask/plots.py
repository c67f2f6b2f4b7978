"""Figures a user looks at: projection panels (speckle, phase, attenuation, residual),
tomogram slices, FSC curves and benchmark charts."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (headless workers, CI)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path) -> Path:
    """Lay out, write at 90 dpi and close (figures are made in loops; close frees them)."""
    fig.tight_layout()
    fig.savefig(path, dpi=90, bbox_inches="tight")
    pyplot().close(fig)
    return Path(path)


def projection_panels(
    path: str | Path, *, sample, reference, result, truth_phase=None, truth_attenuation=None, pixel_size_m: float = 1.0
) -> Path:
    """PNG of the speckle images, retrieved phase and attenuation, residual (and the truth).
    ``sample``/``reference`` or ``result.residual`` None leave their panels out."""
    plt = pyplot()
    from pwf_dask.backend import to_numpy

    method = str(getattr(result, "parameters", {}).get("method", "PWF")).upper()
    panels = [
        ("sample speckle", sample, "gray", "intensity / flat"),
        ("reference speckle", reference, "gray", "intensity / flat"),
        (f"{method} phase", result.phase, "viridis", "rad"),
        ("true phase", truth_phase, "viridis", "rad"),
        (f"{method} attenuation", result.attenuation, "magma", "-ln|T|"),
        ("true attenuation", truth_attenuation, "magma", "-ln|T|"),
        ("residual |y - f|", result.residual, "inferno", "% of mean reference"),
    ]
    panels = [(t, to_numpy(img), c, u) for t, img, c, u in panels if img is not None]
    # a retrieved panel shares its truth's colour range, so that the two compare by eye
    ranges = {t.split()[-1]: np.nanpercentile(img, [0.5, 99.5]) for t, img, _, _ in panels if t.startswith("true")}
    ncol = min(4, len(panels))
    nrow = int(np.ceil(len(panels) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4 * ncol, 3.6 * nrow), squeeze=False)
    for ax, (title, img, cmap, unit) in zip(axes.flat, panels):
        ny, nx = img.shape
        ext_um = [0, nx * pixel_size_m * 1e6, ny * pixel_size_m * 1e6, 0]
        vmin, vmax = ranges.get(title.split()[-1], np.nanpercentile(img, [0.5, 99.5]))
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, extent=ext_um)
        ax.set_title(title)
        ax.set_xlabel("x (µm)")
        ax.set_ylabel("y (µm)")
        fig.colorbar(im, ax=ax, shrink=0.8, label=unit)
    for ax in list(axes.flat)[len(panels) :]:
        ax.axis("off")
    fig.suptitle(
        f"{method}: {result.iterations} iterations, converged={result.converged}, "
        f"residual RMSE {result.residual_rmse:.2f} % of the mean reference"
    )
    return save_figure(fig, path)


def bench_ratio_plot(path: str | Path, rows: list[dict]) -> Path:
    """Iteration time / FFT time per size, one line per variant (dotted: the line-by-line port)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 4))
    for variant, threads in sorted({(r["variant"], r.get("fft_workers", 1)) for r in rows}):
        sel = [r for r in rows if r["variant"] == variant and r.get("fft_workers", 1) == threads]
        label = f"{variant}, {threads} thread{'s' if int(threads) > 1 else ''}"
        (line,) = ax.plot([r["pixels"] for r in sel], [r["ratio"] for r in sel], "o-", label=label)
        printed = [
            (r["pixels"], r["literal_ratio"]) for r in sel if math.isfinite(float(r.get("literal_ratio", "nan")))
        ]
        if printed:
            ax.plot(*zip(*printed), "x:", color=line.get_color())
    ax.plot([], [], "kx:", label="Algorithms S1/S2 as printed (same variant)")
    ax.set_xscale("log")
    ax.set_xlabel("pixels per projection")
    ax.set_ylabel("PWF iteration time / complex64 FFT time")
    ax.axhline(20, color="gray", ls="--", lw=1)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return save_figure(fig, path)


def decade(values) -> int:
    """The power of ten that brings the values' robust maximum into [1, 10) (colour-bar units)."""
    top = float(np.nanpercentile(np.abs(values), 99.5)) if np.size(values) else 0.0
    return int(np.floor(np.log10(top))) if top > 0 and np.isfinite(top) else 0


def tomogram_panels(path: str | Path, recon, truth=None) -> Path:
    """delta and beta slices (middle row, every position; and the truth's, a (delta, beta) pair
    of (v, u) slices, where the scan is simulated), colour bars in labelled powers of ten."""
    plt = pyplot()
    npos = recon.sizes["position"]
    mid = recon.sizes["y"] // 2
    ncol = npos + (truth is not None)
    fig, axes = plt.subplots(2, ncol, figsize=(4.4 * ncol, 7.6), squeeze=False)
    u = recon["u"].values * 1e6
    v = recon["v"].values * 1e6
    ext = [u[0], u[-1], v[0], v[-1]]
    y_um = recon["y"].values[mid] * 1e6
    for row, (name, cmap) in enumerate((("delta", "gray"), ("beta", "magma"))):
        slices = [(f"position {p}", recon[name][p, mid].values) for p in range(npos)]
        if truth is not None:
            slices.append(("truth", np.asarray(truth[row])))
        e = decade(slices[0][1])
        # one colour range per row, the truth's where there is one, so that columns compare
        lo, hi = np.nanpercentile(slices[-1][1], [1, 99.8]) / 10.0**e
        for col, (what, img) in enumerate(slices):
            ax = axes[row, col]
            im = ax.imshow(img / 10.0**e, origin="lower", cmap=cmap, extent=ext, vmin=lo, vmax=hi)
            ax.set_title(f"{name}, {what}, y = {y_um:.1f} µm", fontsize=10)
            ax.set_xlabel("u (µm)")
            ax.set_ylabel("v (µm)")
            fig.colorbar(im, ax=ax, shrink=0.8, label=f"{name} / 1e{e}")
    return save_figure(fig, path)


def fsc_plot(path: str | Path, recon) -> Path:
    """FSC curves with their criteria and resolutions."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    f = recon["frequency"].values * 1e-6
    for ax, name in zip(axes, ("delta", "beta")):
        da = recon[f"fsc_{name}"]
        for i in range(da.sizes["split"]):
            ax.plot(f, da[i].values, color="C0", alpha=0.4)
        ax.plot(
            f,
            da.values.mean(axis=0),
            color="C0",
            lw=2,
            label=f"{da.attrs['split']}: {da.attrs['resolution_m'] * 1e6:.2f} µm at {da.attrs['criterion']}",
        )
        ax.axhline(0.25, color="C0", ls=":")
        if f"fsc_{name}_truth" in recon:
            t = recon[f"fsc_{name}_truth"]
            ax.plot(
                f,
                t.values.mean(axis=0),
                color="C1",
                lw=2,
                label=f"vs truth: {t.attrs['resolution_m'] * 1e6:.2f} µm at 1/2",
            )
            ax.axhline(0.5, color="C1", ls=":")
        ax.set_xlabel("spatial frequency (cycles/µm)")
        ax.set_ylabel("FSC")
        ax.set_title(name)
        ax.set_ylim(-0.2, 1.05)
        ax.legend(fontsize=8)
    return save_figure(fig, path)


def default_figure_dir(recon_path: str | Path) -> Path:
    """``RECON_figures`` beside a local store (``recon.zarr`` -> ``recon_figures``); for a URL,
    in the working directory."""
    text = str(recon_path).rstrip("/")
    name = text.rsplit("/", 1)[-1].removesuffix(".zarr") + "_figures"
    return Path(name) if "://" in text else Path(text).parent / name


def _preview_projection(ds, out: Path) -> Path | None:
    """projection.png of the first retrieved projection, with the stored residual when it is
    the first angle's, the scan's speckle images when the scan can be read, and the truth when
    the scan is simulated."""
    from types import SimpleNamespace

    from pwf_dask.physics import optics
    from pwf_dask.simulation import phantom_from_json
    from pwf_dask.stores import scan_io

    done = np.argwhere(ds["iterations"].values >= 0)
    if not len(done):
        return None
    p, a = (int(i) for i in done[0])
    residual = None
    if a == 0 and "preview_residual" in ds and np.isfinite(ds["preview_residual"][p].values).any():
        residual = ds["preview_residual"][p].values
    result = SimpleNamespace(
        phase=ds["phase"][p, a].values,
        attenuation=ds["attenuation"][p, a].values,
        residual=residual,
        iterations=int(ds["iterations"][p, a]),
        converged=bool(ds["converged"][p, a]),
        residual_rmse=float(ds["residual_rmse"][p, a]),
        parameters={"method": ds.attrs.get("method", "pwf")},
    )
    sample = reference = None
    try:
        sds, info = scan_io.open_scan(ds.attrs["scan"], check_values=False)
        flat = sds["flat"].values if info.has_flat else None
        dark = sds["dark"].values if info.has_dark else None
        sample = scan_io.correct(sds["projections"][p, a].values, flat, dark, info.flat_dark_corrected)
        reference = scan_io.correct(sds["reference"][p].values, flat, dark, info.flat_dark_corrected)
    except (KeyError, scan_io.ScanError):
        pass  # the scan moved or is not readable here: the retrieved panels alone
    truth_phase = truth_att = None
    if "simulation_phantom" in ds.attrs:
        k = 2 * np.pi / optics.wavelength_m(float(ds.attrs["energy_eV"]))
        phantom = phantom_from_json(ds.attrs["simulation_phantom"])
        d_int, b_int = phantom.line_integrals(
            float(ds["angle"][a]), ds["x"].values, ds["y"].values, float(ds.attrs["energy_eV"])
        )
        truth_phase, truth_att = -k * d_int, k * b_int
    return projection_panels(
        out / "projection.png",
        sample=sample,
        reference=reference,
        result=result,
        truth_phase=truth_phase,
        truth_attenuation=truth_att,
        pixel_size_m=float(ds.attrs["pixel_size_m"]),
    )


def preview(recon_path: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """The figures of a reconstruction, as far as it goes (``pwf-dask preview``): projection
    panels, delta/beta slices (with the truth's for a simulated scan) and FSC curves."""
    import xarray as xr

    from pwf_dask.simulation import phantom_from_json, refractive_index_volume

    ds = xr.open_zarr(str(recon_path))
    out = Path(out_dir) if out_dir is not None else default_figure_dir(recon_path)
    out.mkdir(parents=True, exist_ok=True)
    figures = [_preview_projection(ds, out)]
    if "delta" in ds and "tomo_done" in ds and int(ds["tomo_done"].values.min()) == 1:
        truth = None
        if "simulation_phantom" in ds.attrs:
            # three rows about the middle: the voxel average needs the row spacing
            mid = ds.sizes["y"] // 2
            first = max(mid - 1, 0)
            d, b = refractive_index_volume(
                phantom_from_json(ds.attrs["simulation_phantom"]),
                ds["y"].values[first : mid + 2],
                ds["v"].values,
                ds["u"].values,
                float(ds.attrs["energy_eV"]),
            )
            truth = (d[mid - first], b[mid - first])
        figures.append(tomogram_panels(out / "tomograms.png", ds, truth))
    if "fsc_delta" in ds:
        figures.append(fsc_plot(out / "fsc.png", ds))
    return [f for f in figures if f is not None]
