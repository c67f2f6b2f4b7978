"""The default simulated scan (preset ``beads``: a glass bead of the paper's size in the
paper's toothpick slab) and the ``small`` preset's beads of 3.5 coherence lengths,
reconstructed with every default: bead delta and beta against xraydb, and PWF with one
diffuser position against LCS with twelve (the paper's headline)."""

import numpy as np
import pytest
import xarray as xr
from measures import bead_errors, bead_values, lcs12, under_papers_fit

from pwf_dask import cli
from pwf_dask.physics.materials import delta_beta
from pwf_dask.pipeline import workflow
from pwf_dask.simulation import PAPER_BEAD_RADIUS_M, PRESETS, phantom_from_json, scan_phantom, simulate_scan


def test_default_preset_holds_beads_of_the_papers_size():
    """``beads`` (the default) and ``paper`` draw the paper's <= 106 um beads, not beads scaled
    to the frame; a smaller frame shrinks them to fit its height and the cylinder."""
    p = 0.65e-6
    assert cli.build_parser().parse_args(["simulate", "x.zarr"]).preset == "beads"
    assert PRESETS["beads"]["bead_radius_m"] == PRESETS["paper"]["bead_radius_m"] == PAPER_BEAD_RADIUS_M
    lo, hi = PAPER_BEAD_RADIUS_M
    paper = scan_phantom(PRESETS["paper"]["shape"], p, 0, None, PAPER_BEAD_RADIUS_M)
    radii = np.array([sp.radius_m for sp in paper.spheres])
    assert len(radii) > 50 and radii.min() >= lo and radii.max() == hi
    slab = scan_phantom(PRESETS["beads"]["shape"], p, 0, None, PAPER_BEAD_RADIUS_M)
    assert max(sp.radius_m for sp in slab.spheres) == pytest.approx(0.4 * 160 * p)  # 83 um across
    for shape in ((32, 64), (48, 40)):
        small = scan_phantom(shape, p, 1, None, PAPER_BEAD_RADIUS_M)
        for sp in small.spheres:
            assert abs(sp.y_m) + sp.radius_m <= 0.5 * shape[0] * p
            assert np.hypot(sp.u_m, sp.v_m) + sp.radius_m <= small.cylinder_radius_m


#: angles of the ``beads`` scan the tests reconstruct (of the preset's 121)
BEADS_TEST_ANGLES = 17


@pytest.fixture(scope="module")
def beads_recon(tmp_path_factory):
    """The default simulated scan (preset ``beads``: the paper's toothpick slab with a glass
    bead of the paper's size, 83 um across, radius ~12 coherence lengths), one position and
    17 of its 121 angles to save time, reconstructed with the defaults: bead delta / beta
    -2.75 % / +1.34 % of xraydb, LCS K = 12 +2.22 % / -1.01 % (session 75, the default slice
    background "auto"); under the paper's slice fit -3.14 % / -3.72 % against +4.68 % / -41.7 %
    (session 59: 21 angles -3.26 % / -3.47 % against +4.90 %, 25 angles -2.82 % / -3.08 %
    against +4.91 %: the margins of 25 angles were kept until the suite's time passed the
    brief's 15 minutes on CI)."""
    d = tmp_path_factory.mktemp("beads")
    scan, recon = d / "scan.zarr", d / "recon.zarr"
    simulate_scan(scan, angles=BEADS_TEST_ANGLES, positions=1, seed=0, rotation_axis_offset_px=2.5, progress=False)
    # retrieval and tomography as ``run`` does them; no test here reads its FSC
    workflow.retrieve_scan(scan, recon)
    workflow.tomo_scan(recon)
    return xr.open_zarr(recon)


@pytest.mark.slow
def test_glass_bead_delta_within_5_percent(beads_recon):
    assert beads_recon.attrs["simulation_preset"] == "beads" and beads_recon.attrs["alpha"] == "0.1+0.05j"
    dg, _ = delta_beta("soda-lime glass", beads_recon.attrs["energy_eV"])
    d, _ = bead_values(beads_recon, 0)
    assert d == pytest.approx(dg, rel=0.05)


def test_glass_bead_beta_within_20_percent(beads_recon):
    _, bg = delta_beta("soda-lime glass", beads_recon.attrs["energy_eV"])
    _, b = bead_values(beads_recon, 0)
    assert b == pytest.approx(bg, rel=0.2)


@pytest.mark.slow
def test_beads_of_three_coherence_lengths_delta_within_10_percent(tmp_path):
    """Issue #27: the ``small`` preset's largest bead is 18.4 px (12 µm, 3.5 calibrated
    coherence lengths) in radius; one position, 21 angles, every default (alpha 0.1+0.05j,
    calibrated coherence). Measured bead delta +9.5 % (seed 0; +4.3 % with seed 1; 31 angles
    +9.9 % on seed 0) under the default slice background since session 75 ("auto", which
    leaves these slices bare), near the bound: the bead overshoots, and the paper's slice
    fit, whose level takes ~5 points off it, read +4.8 % / +2.6 % (session 66; at 31 angles
    +5.3 % / +3.3 %, at 41 +5.6 % / +3.8 %, at 61 +6.1 % / +2.5 %; +6.7 % / -3.1 % at the
    preset's 121 angles and two positions; 15 angles +2.2 % / +1.4 %). Its beta reads -7.2 %
    / -1.6 % bare against -15.5 % / -9.5 % fitted. The demo's 2 coherence lengths read
    -2.3 % / -1.3 % bare (-10.3 % / -1.5 % fitted; test_demo_scan.py)."""
    scan, recon = tmp_path / "small.zarr", tmp_path / "r.zarr"
    simulate_scan(scan, preset="small", angles=21, positions=1, seed=0, progress=False)
    workflow.retrieve_scan(scan, recon)
    workflow.tomo_scan(recon)
    ds = xr.open_zarr(recon)
    bead = max(phantom_from_json(ds.attrs["simulation_phantom"]).spheres, key=lambda s: s.radius_m)
    assert 3.0 < bead.radius_m / ds.attrs["coherence_length_x_m"] < 4.0
    dg, _ = delta_beta("soda-lime glass", ds.attrs["energy_eV"])
    assert bead_values(ds, 0)[0] == pytest.approx(dg, rel=0.1)


@pytest.fixture(scope="module")
def lcs12_beads_recon(tmp_path_factory):
    return lcs12(tmp_path_factory, "lcs12beads", angles=BEADS_TEST_ANGLES)  # bead delta +4.68 %


@pytest.mark.slow
def test_pwf_k1_beats_lcs_k12_on_bead_delta_under_the_papers_fit(beads_recon, lcs12_beads_recon, tmp_path):
    """The paper's headline on the default scan (a bead of the paper's size), from measured
    errors, with the paper's tomography: its slice fit over every sample-free pixel."""
    assert lcs12_beads_recon.sizes["position"] == 1 and lcs12_beads_recon.attrs["method"] == "lcs"
    assert lcs12_beads_recon.attrs["simulation_phantom"] == beads_recon.attrs["simulation_phantom"]
    pwf, lcs = under_papers_fit(beads_recon, tmp_path), under_papers_fit(lcs12_beads_recon, tmp_path)
    assert bead_errors(pwf, 0)[0] < bead_errors(lcs, 0)[0]


@pytest.mark.slow
def test_pwf_k1_beats_lcs_k12_on_bead_beta_under_the_papers_fit(beads_recon, lcs12_beads_recon, tmp_path):
    """The paper's beta finding, with the paper's slice fit: LCS's attenuation carries
    phase-coupling artifacts (here on the paper's bead; on the demo's small one in
    test_demo_scan.py), which the fit reads as background and takes the bead down with."""
    pwf, lcs = under_papers_fit(beads_recon, tmp_path), under_papers_fit(lcs12_beads_recon, tmp_path)
    assert bead_errors(pwf, 0)[1] < bead_errors(lcs, 0)[1]


@pytest.mark.slow
def test_under_the_default_slice_background_both_methods_hold_the_bead(beads_recon, lcs12_beads_recon):
    """Under the default slice background ("auto", which leaves these slices unfitted: the
    slab's halo covers every sample-free pixel) PWF K = 1 and LCS K = 12 both read the
    paper's bead within 3 % in delta and 2 % in beta; the paper's fit is what set them apart."""
    assert beads_recon.attrs["slice_background"] == lcs12_beads_recon.attrs["slice_background"] == "auto"
    for ds in (beads_recon, lcs12_beads_recon):
        delta_error, beta_error = bead_errors(ds, 0)
        assert delta_error < 0.03 and beta_error < 0.02, ds.attrs["method"]
