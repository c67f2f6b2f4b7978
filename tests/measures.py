"""What the accuracy tests measure a result by, and the K = 12 LCS scan they hold PWF's
against; written once for their modules."""

import shutil
from pathlib import Path

import numpy as np
import xarray as xr

from benchmarks.demo_dose import cylinder_values  # noqa: F401 (the tests' measure too)
from pwf_dask.physics.materials import delta_beta
from pwf_dask.pipeline import workflow
from pwf_dask.simulation import phantom_from_json, simulate_scan


def kwargs(sim, **extra):
    """A simulated projection's (or a SpeckleSetup's) geometry as retrieve_projection's keywords."""
    return {**sim.geometry(), **extra}


def gain(recovered, truth, inside):
    """Regression slope of recovered on true values over ``inside`` (offset free)."""
    return float(np.polyfit(truth[inside], np.asarray(recovered)[inside], 1)[0])


def relative_phase_error(res, sim) -> float:
    """rms phase error over the sample (true phase below -0.5 rad), relative to the true phase's rms there."""
    inside = sim.phase < -0.5
    return float(np.sqrt(np.mean((res.phase - sim.phase)[inside] ** 2) / np.mean(sim.phase[inside] ** 2)))


def bead_values(ds, p):
    """Mean delta and beta of a reconstruction's largest simulated bead, inside half its radius,
    at diffuser position ``p``."""
    ph = phantom_from_json(ds.attrs["simulation_phantom"])
    bead = max(ph.spheres, key=lambda s: s.radius_m)
    Y, V, U = np.meshgrid(ds.y.values, ds.v.values, ds.u.values, indexing="ij")
    ins = (Y - bead.y_m) ** 2 + (V - bead.v_m) ** 2 + (U - bead.u_m) ** 2 < (0.5 * bead.radius_m) ** 2
    return float(ds.delta[p].values[ins].mean()), float(ds.beta[p].values[ins].mean())


def under_papers_fit(ds, tmp_path):
    """A reconstruction's store copied and its tomograms made again under the paper's slice fit
    (``slice_background="quadratic"``): the tomography the paper compares its methods with."""
    source = Path(ds.encoding["source"])
    copy = tmp_path / f"{source.parent.name}-{source.stem}-quadratic.zarr"
    shutil.copytree(source, copy)
    workflow.tomo_scan(copy, slice_background="quadratic")
    return xr.open_zarr(copy)


def lcs12(tmp_path_factory, name, **scene):
    """The scene's phantom with K = 12 diffuser positions (position 0 is the PWF scan's
    diffuser), reconstructed by LCS from all twelve (retrieval and tomography; the tests
    compare bead values, not the FSC ``run`` would add)."""
    d = tmp_path_factory.mktemp(name)
    scan, recon = d / "scan.zarr", d / "recon.zarr"
    simulate_scan(scan, positions=12, seed=0, rotation_axis_offset_px=2.5, progress=False, **scene)
    workflow.retrieve_scan(scan, recon, method="lcs")
    workflow.tomo_scan(recon)
    return xr.open_zarr(recon)


def bead_errors(ds, p):
    """|relative error| of the largest bead's delta and beta against xraydb's soda-lime glass."""
    dg, bg = delta_beta("soda-lime glass", ds.attrs["energy_eV"])
    d, b = bead_values(ds, p)
    return abs(d / dg - 1), abs(b / bg - 1)
