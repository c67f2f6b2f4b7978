"""The demo scan (``pwf-dask demo``: 48 x 128, two diffuser positions, 150 iterations at most)
on 31 of its 61 angles, reconstructed with its settings: the calibration it records, the
rotation axis, cylinder and small-bead delta and beta against xraydb, FSC; beside it LCS with
K = 12, and the same scan made an interior scan (the cylinder wider than the field of view).

The measures read the same on 31 angles as on the demo's 61 (session 55, positions 0 / 1; 150
iterations): cylinder -14.9 / -7.2 % against -14.9 / -9.2 %, bead delta -10.3 / -1.5 % against
-10.2 / -4.3 %, bead beta -6.5 / +2.0 % against -3.1 / +4.7 %, rotation axis within 0.01 px
either way, in 0.5x the time; LCS K = 12 bead delta +3.5 % against +4.0 %, beta +27 % against
+79 % (docs/validation.md, Scan-level findings, 10). Those were under the paper's slice fit;
under the default since session 75 ("auto", which leaves the demo's slices unfitted) the 31
angles read cylinder -2.2 / -3.8 %, bead delta -2.3 / -1.3 %, bead beta -6.3 / +1.6 %, LCS
K = 12 bead delta +2.1 %, beta +1.0 %."""

import json

import numpy as np
import pytest
import xarray as xr
from measures import bead_errors, bead_values, cylinder_values, lcs12

from pwf_dask import calibration, cli
from pwf_dask.physics.materials import delta_beta
from pwf_dask.pipeline import workflow
from pwf_dask.simulation import phantom_from_json, refractive_index_volume, simulate_scan

#: the demo's 61 angles thinned to 31 (the module's docstring: the measures read the same)
DEMO_TEST_ANGLES = 31


@pytest.fixture(scope="module")
def demo_recon(tmp_path_factory):
    d = tmp_path_factory.mktemp("demo")
    scan, recon = d / "scan.zarr", d / "recon.zarr"
    simulate_scan(scan, preset="demo", angles=DEMO_TEST_ANGLES, seed=0, rotation_axis_offset_px=2.5, progress=False)
    # the demo's settings (its iteration cap; defaults otherwise)
    workflow.run_scan(scan, recon, max_iter=cli.DEMO_MAX_ITER)
    return xr.open_zarr(recon)


def test_the_store_records_each_positions_calibration_and_the_dose_it_read(demo_recon):
    """The demo's raw counts (1e4 ph/px, flat- and dark-corrected, through the diffuser) read
    6.6e3 photons a pixel: above the calibration's low-dose frequency choice."""
    fits = json.loads(demo_recon.attrs["coherence_fits_per_position"])
    assert len(fits) == demo_recon.sizes["position"]
    for fit in fits:
        assert fit["method"] == "template"
        assert calibration.coherence.LOW_DOSE_PHOTONS < fit["reference_photons_per_px"] < 1e4


@pytest.mark.slow
def test_rotation_axis_found(demo_recon):
    true = demo_recon.attrs["simulation_rotation_axis_offset_m"]
    assert abs(demo_recon.attrs["rotation_center_m"] - true) < 0.1 * demo_recon.attrs["pixel_size_m"]


def test_cylinder_delta_within_20_percent(demo_recon):
    """The demo's 48 rows hold seven P3000 grains: its weak wide cylinder reads -3.9 % / -5.6 %
    at the two positions with every default (the mean of its bead-free core; the median of the
    whole core, beads in it, read -2.2 % / -3.8 %; session 76), -14.9 % / -7.2 % (median) under
    the paper's slice fit, which reads the cylinder's halo as background. Under that fit, on
    all 61 angles: -14.9 % / -9.2 % (-16.0 % / -7.8 % at 300 iterations); at 300 iterations
    with the paper's alpha -11.6 % / -2.6 %, and -10.8 % / -2.2 % with the true coherence
    lengths too; -2 % to -4 % on the finer pre-P3000
    sandpaper. The cylinder alone in single projections reads 0.923 of its phase in the median
    of 45 draws at 48-768 rows and three grains (0.71-1.08 by the draw, each draw's angles
    alike; no trend in height: benchmarks/results/cylinder_rows.md), and with noise-free images,
    the true lengths and the true diffuser the default alpha still holds it at 0.83 / 0.92 on
    two low draws (cylinder_rows_why.md: the regularizer's bias). Open in #27."""
    dc, _ = delta_beta("cellulose", demo_recon.attrs["energy_eV"])
    for p in range(2):
        assert cylinder_values(demo_recon, p)[0] == pytest.approx(dc, rel=0.2)


def test_cylinder_beta_within_25_percent(demo_recon):
    """The cellulose's own beta (its bead-free core; cellulose's beta is 1/637 of its delta
    at 10 keV, so beta is the noisiest number of the scan): -10.3 % / +2.9 % at the two
    positions with every default. Converged, -8.6 % / +4.3 % bare (the default "auto" on the
    demo) against -33.0 % / -19.6 % under the paper's slice fit, which takes beta's positive
    level beyond the rim's artefacts (+0.2 to +0.6 of cellulose's beta at 1.25-2 radii) as
    background. This is one draw: over seeds 0-3 the converged scans read -24 % to +81 %
    (median |error| 12.5 % under "auto", 22 % under the paper's fit; session 76,
    docs/validation.md)."""
    _, bc = delta_beta("cellulose", demo_recon.attrs["energy_eV"])
    for p in range(2):
        assert cylinder_values(demo_recon, p)[1] == pytest.approx(bc, rel=0.25)


def test_demo_small_bead_delta_within_5_percent(demo_recon):
    """The demo's beads are 12 px (2 coherence lengths) in radius on the paper's diffuser:
    -2.3 % / -1.3 % at the two positions under the default slice background ("auto", which
    leaves the demo's slices unfitted: the cylinder's halo covers every sample-free pixel);
    -10.3 % / -1.5 % under the paper's fit, which read the halo as background (session 75;
    docs/validation.md). +19 % / +14 % with the paper's alpha on the finer diffuser of
    sessions 1-21."""
    dg, _ = delta_beta("soda-lime glass", demo_recon.attrs["energy_eV"])
    d, _ = bead_values(demo_recon, 0)
    assert d == pytest.approx(dg, rel=0.05)


def test_demo_small_bead_beta_within_20_percent(demo_recon):
    """-6.5 % / +2.0 % with the default alpha (-3.1 % / +4.7 % on all 61 angles; 0.72 / 0.82 of
    xraydb with the paper's at 300 iterations: Re(alpha) damps small absorbers and the phase took their signal)."""
    _, bg = delta_beta("soda-lime glass", demo_recon.attrs["energy_eV"])
    _, b = bead_values(demo_recon, 0)
    assert b == pytest.approx(bg, rel=0.2)


def test_every_variable_and_coordinate_has_units_and_a_long_name(demo_recon):
    """CF-style attributes (issue #28): xarray's own plots label their axes in metres."""
    for name in [*demo_recon.data_vars, *demo_recon.coords]:
        attrs = demo_recon[name].attrs
        assert attrs.get("units") and attrs.get("long_name"), name
    assert demo_recon.u.attrs["units"] == "m" and demo_recon.delta.attrs["long_name"].startswith("refractive")


def test_fsc_resolutions_are_physical(demo_recon):
    p = demo_recon.attrs["pixel_size_m"]
    for name in ("fsc_delta", "fsc_beta", "fsc_delta_truth"):
        r = demo_recon[name].attrs["resolution_m"]
        assert 2 * p <= r < 30 * p, (name, r)


@pytest.fixture(scope="module")
def lcs12_recon(tmp_path_factory):
    return lcs12(tmp_path_factory, "lcs12", preset="demo", angles=DEMO_TEST_ANGLES)


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="measured (session 75): under the default slice background LCS K=12's small-bead beta is +1.0 %, "
    "PWF K=1's -6.3 %; LCS's +27 % against PWF's -6.5 % under the paper's fit was the fit reading LCS's "
    "beta halo as background (docs/validation.md); the paper's bead: test_beads_scan.py",
)
def test_pwf_k1_beats_lcs_k12_on_the_small_bead_beta(demo_recon, lcs12_recon):
    """The paper's beta finding on the demo's small bead (LCS's attenuation carries
    phase-coupling artifacts)."""
    assert lcs12_recon.sizes["position"] == 1 and lcs12_recon.attrs["method"] == "lcs"
    assert bead_errors(demo_recon, 0)[1] < bead_errors(lcs12_recon, 0)[1]


@pytest.mark.xfail(
    strict=True,
    reason="measured, where the paper's headline reverses: on the demo's 12-px beads LCS K=12 bead delta "
    "is +2.1 %, PWF K=1 -2.3 % with the defaults on the paper's diffuser (+3.5 % / -10.3 % under the "
    "paper's slice fit; docs/validation.md)",
)
def test_demo_small_bead_pwf_k1_beats_lcs_k12_on_bead_delta(demo_recon, lcs12_recon):
    assert bead_errors(demo_recon, 0)[0] < bead_errors(lcs12_recon, 0)[0]


@pytest.fixture(scope="module")
def interior_recon(tmp_path_factory):
    """The demo scan (one position, 31 of its 61 angles) with the cylinder 1.5x as wide as the
    field of view: no angle has a sample-free pixel (an interior scan); the beads are those of
    the demo scan. The measures below read the same at 61 angles (session 54, 300 iterations:
    structure 0.094 of cellulose's delta against 0.093, level -71 % against -74 %) in twice the
    time, and at 300 iterations as at the demo's 150 (session 55: 0.093, -74 % / -74.5 %)."""
    d = tmp_path_factory.mktemp("interior")
    scan, recon = d / "scan.zarr", d / "recon.zarr"
    assert (
        cli.main(
            ["simulate", str(scan), "--preset", "demo", "--positions", "1", "--axis-offset-px", "2.5"]
            + ["--angles", "31", "--cylinder-width-fraction", "1.5"]
        )
        == 0
    )
    workflow.retrieve_scan(scan, recon, max_iter=cli.DEMO_MAX_ITER)
    workflow.tomo_scan(recon)  # as ``run``, without the FSC no measure here reads
    ds = xr.open_zarr(recon)
    ph = phantom_from_json(ds.attrs["simulation_phantom"])
    truth, _ = refractive_index_volume(ph, ds.y.values, ds.v.values, ds.u.values, ds.attrs["energy_eV"])
    V, U = np.meshgrid(ds.v.values, ds.u.values, indexing="ij")
    seen = np.hypot(V, U) < 0.9 * ds.u.values.max()  # inside the field of view at every angle
    return ds, truth, seen


@pytest.mark.slow
def test_interior_scan_keeps_the_structure_up_to_one_constant_per_slice(interior_recon):
    """Nothing of the sample is sample-free, so no projection's phase level can be known; the
    structure can: minus its mean offset per slice, delta errs as on the demo scan (0.11 of
    cellulose's delta measured on both in session 17; 0.093 here in session 54)."""
    ds, truth, seen = interior_recon
    dc, _ = delta_beta("cellulose", ds.attrs["energy_eV"])
    err = ds.delta[0].values[:, seen] - truth[:, seen]
    err -= err.mean(axis=1, keepdims=True)
    assert np.sqrt(np.mean(err**2)) < 0.2 * dc


@pytest.mark.xfail(
    strict=True,
    reason="known, every method: an interior scan loses the level of delta (cellulose -77 %; "
    "docs/validation.md, Where PWF fails): no projection has a sample-free pixel to zero its phase on",
)
def test_interior_scan_keeps_the_level_of_delta(interior_recon):
    ds, truth, seen = interior_recon
    dc, _ = delta_beta("cellulose", ds.attrs["energy_eV"])
    matrix = truth[:, seen] == dc
    assert float(np.median(ds.delta[0].values[:, seen][matrix])) == pytest.approx(dc, rel=0.1)
