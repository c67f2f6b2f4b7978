"""The scan pipeline: schedulers, resume, bad scans, quantitative tomograms (CONTRACT §1-3)."""

import json
import logging
import shutil
import threading
import time

import numpy as np
import pytest
import xarray as xr
import zarr

from pwf_dask import cli
from pwf_dask.calibration import SensitivityLimits
from pwf_dask.physics.materials import delta_beta
from pwf_dask.pipeline import workflow
from pwf_dask.pwf import solver
from pwf_dask.simulation import (
    phantom_from_json,
    simulate_scan,
)
from pwf_dask.stores import scan_io

FAST = dict(max_iter=25, tol=0.0)


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory):
    path = tmp_path_factory.mktemp("scan") / "tiny.zarr"
    simulate_scan(path, preset="demo", shape=(32, 64), angles=9, positions=2, seed=3, progress=False)
    return path


@pytest.fixture(scope="module")
def fast_recon(tiny_scan, tmp_path_factory):
    """``tiny_scan`` retrieved once with ``FAST`` on the threaded scheduler: the reference the
    tests below compare with (read only; a test that writes to it takes a copy)."""
    path = tmp_path_factory.mktemp("fast") / "threads.zarr"
    workflow.retrieve_scan(tiny_scan, path, scheduler="threads", **FAST)
    return path


def stores_equal(a, b):
    da, db = xr.open_zarr(a), xr.open_zarr(b)
    for name in ("phase", "attenuation", "iterations", "residual_rmse"):
        np.testing.assert_allclose(da[name].values, db[name].values, rtol=1e-5, atol=1e-6)


def test_contract_layout(tiny_scan, tmp_path):
    recon = tmp_path / "r.zarr"
    workflow.run_scan(tiny_scan, recon, **FAST)
    ds = xr.open_zarr(recon)
    assert ds["phase"].dims == ("position", "angle", "y", "x")
    assert ds["delta"].dims == ("position", "y", "v", "u") and ds["beta"].dims == ("position", "y", "v", "u")
    assert ds["fsc_delta"].dims == ("split", "frequency")
    assert {"resolution_m", "criterion"} <= set(ds["fsc_delta"].attrs)
    for key in (
        "method",
        "gamma",
        "alpha",
        "step",
        "tol",
        "max_iter",
        "coherence_length_x_m",
        "coherence_length_y_m",
        "pwf_dask_version",
    ):
        assert key in ds.attrs, key
    # the default rule keeps the fixed alpha where the data see the phase as the paper's scene does
    assert ds.attrs["alpha"] == "0.1+0.05j" and ds.attrs["alpha_rule"] == "sensitivity"
    assert ds.attrs["phase_sensitivity"] > 0.015
    assert (ds["iterations"].values == 25).all()
    # sinogram slabs are one chunk per angle: chunks hold whole rows of one angle
    assert ds["phase"].encoding["chunks"][:2] == (1, 1)
    assert ds["phase"].encoding["chunks"][3] == ds.sizes["x"]
    # what the speckle could carry, per projection (calibration.sensitivity): the demo's optics
    # carry the phase, even as far as 25 iterations have built it (0.05-0.07 of the grain)
    limits = SensitivityLimits()
    assert (ds["speckle_shift_over_grain"].values > limits.min_shift_over_grain).all()
    assert (ds["speckle_visibility"].values > 2 * limits.min_visibility).all()
    # and its fit leaves no more misfit in the sample than in the background
    assert (ds["sample_misfit"].values < limits.max_sample_misfit).all()


def test_a_run_says_in_one_line_where_the_data_carry_little_of_the_phase(fast_recon, monkeypatch, caplog):
    """The stored measures reach the run's summary: with limits above the demo's values every
    projection is counted, in one warning; with the real limits the speckle's measures say
    nothing, and this 25-iteration run's two positions disagree on some angles (converged, the
    demo scan's read 0.05-0.20: docs/validation.md)."""
    import pwf_dask.calibration as calibration

    grp = zarr.open_group(str(fast_recon), mode="r")
    with caplog.at_level(logging.WARNING, logger="pwf_dask.pipeline.workflow"):
        workflow._warn_sensitivity(grp)
        (record,) = caplog.records
        assert record.getMessage().startswith("retrieve: warning: the diffuser positions' phases disagree")
        caplog.clear()
        limits = SensitivityLimits(10.0, 0.0, max_position_disagreement=np.inf)
        monkeypatch.setattr(calibration, "SensitivityLimits", lambda: limits)
        workflow._warn_sensitivity(grp)
    (record,) = caplog.records
    assert "under 10 of its grain on 18 of 18 projections" in record.getMessage()
    assert "disagree" not in record.getMessage()


def test_a_scan_of_two_positions_stores_their_disagreement_per_angle(fast_recon):
    """K = 2: every angle's two phases compared (calibration.position_disagreement), the same
    number for both positions, stored with the projections' other checks."""
    from pwf_dask.calibration import position_disagreement

    ds = xr.open_zarr(fast_recon)
    apart = ds["position_disagreement"]
    assert apart.dims == ("position", "angle") and apart.shape == (2, 9) and apart.attrs["units"] == "1"
    assert np.isfinite(apart.values).all()
    np.testing.assert_allclose(apart.values[0], apart.values[1], rtol=1e-6)
    np.testing.assert_allclose(apart.values[:, 4], position_disagreement(ds.phase.values[:, 4]), rtol=1e-6)


def test_fsc_compares_a_central_sub_volume_of_a_large_scan(tiny_scan, tmp_path, monkeypatch):
    """Issue #29: the FSC's half-tomograms are made in the client; beyond FSC_MAX_ROWS rows or
    FSC_MAX_PX pixels across only the central sub-volume is compared (here 16 x 40 x 40 of 32 x
    64 x 64), so its memory is bounded whatever the scan; within the bounds, the whole."""
    from pwf_dask.tomo import fsc

    assert workflow.fsc_region(32, 64) == (slice(0, 32), slice(0, 64))
    monkeypatch.setattr(workflow, "FSC_MAX_ROWS", 16)
    monkeypatch.setattr(workflow, "FSC_MAX_PX", 40)
    assert workflow.fsc_region(32, 64) == (slice(8, 24), slice(12, 52))
    recon = tmp_path / "r.zarr"
    workflow.run_scan(tiny_scan, recon, **FAST)
    ds = xr.open_zarr(recon)
    pix = ds.attrs["pixel_size_m"]
    cube = np.random.default_rng(0).normal(size=(16, 40, 40))
    np.testing.assert_allclose(ds["frequency"].values, fsc.fourier_shell_correlation(cube, cube, pix)[0])
    assert np.isfinite(ds["fsc_delta"].values).all() and np.isfinite(ds["fsc_delta_truth"].values).all()


@pytest.mark.parametrize("scheduler", ["processes", "local"])
def test_schedulers_give_identical_results(tiny_scan, fast_recon, tmp_path, scheduler):
    other = tmp_path / f"{scheduler}.zarr"
    workflow.retrieve_scan(tiny_scan, other, scheduler=scheduler, **FAST)
    stores_equal(fast_recon, other)


@pytest.mark.gpu
def test_gpu_device_gives_the_cpu_result(cupy, tiny_scan, tmp_path):
    """``--device gpu``: every stage on CuPy arrays (read, diffuser fit, PWF, FBP) writes
    the store the CPU writes, within float32 rounding, but for each slice's background
    quadratic: its sample-free area is a threshold on the slice, where float32 rounding can
    move a pixel across (measured: one slice of 64 whose difference was a quadratic of 3.7e-4
    of delta's maximum, 3e-12 rms left after removing it, as on every other slice). The
    default FBP, gridrec, is finufft on the host and the package's own NUFFT on the device,
    each to 1e-4: their tomograms agree to 2.4e-4 of the maximum (session 73); the
    backprojector is one algorithm on both, to rounding."""
    cpu, gpu = tmp_path / "cpu.zarr", tmp_path / "gpu.zarr"
    for path, device in ((cpu, "cpu"), (gpu, "gpu")):
        workflow.retrieve_scan(tiny_scan, path, device=device, **FAST)
    for fbp, tolerance in (("auto", 5e-4), ("backproject", 1e-4)):
        for path, device in ((cpu, "cpu"), (gpu, "gpu")):
            workflow.tomo_scan(path, device=device, fbp=fbp)
        a, b = xr.open_zarr(cpu), xr.open_zarr(gpu)
        assert b.attrs["device"] == "gpu" and a.attrs["fbp"] == b.attrs["fbp"]
        for name in ("phase", "attenuation", "delta", "beta"):
            scale = float(np.abs(a[name].values).max())
            difference = b[name].values.astype(np.float64) - a[name].values
            if name in ("delta", "beta"):
                quadratics = np.stack([slice_quadratic(s) for s in difference.reshape(-1, *difference.shape[-2:])])
                assert np.abs(quadratics).max() < 1e-3 * scale, name
                difference -= quadratics.reshape(difference.shape)
            assert np.abs(difference).max() < (tolerance if name in ("delta", "beta") else 1e-4) * scale, name


def test_slice_background_fits_the_tomograms_it_names_and_none_is_the_bare_fbp(fast_recon, tmp_path):
    """``slice_background``: "none" writes the FBP itself (the phase and attenuation sinograms
    back-projected and scaled, nothing subtracted), "beta" that FBP for delta and the fitted
    beta of "quadratic", the default "auto" that FBP fitted where delta's slices have
    sample-free pixels beyond the sample's reach, beta on the same slices; the mode is
    recorded, a store made under another is made again, and a bad name is refused in one
    line before anything is written."""
    from pwf_dask.physics.optics import wavelength_m
    from pwf_dask.tomo import tomography

    path = tmp_path / "r.zarr"
    shutil.copytree(fast_recon, path)
    made = {}
    for mode in ("quadratic", "none", "beta", "auto"):
        workflow.tomo_scan(path, slice_background=mode)
        ds = xr.open_zarr(path)
        assert ds.attrs["slice_background"] == mode
        made[mode] = {name: ds[name].values.copy() for name in ("delta", "beta")}
    ds = xr.open_zarr(path)
    k = wavelength_m(ds.attrs["energy_eV"]) / (2 * np.pi)
    for p in range(ds.sizes["position"]):
        for name, var, sign in (("delta", "phase", -k), ("beta", "attenuation", k)):
            fbp = tomography.back_projection(
                ds[var][p].values, ds.angle.values, ds.attrs["pixel_size_m"], ds.attrs["rotation_center_m"]
            )
            # float32 rounding: the stage scales the float32 FBP in place
            np.testing.assert_allclose(made["none"][name][p], sign * fbp, rtol=0, atol=1e-4 * np.abs(fbp).max() * k)
    for p in range(ds.sizes["position"]):
        far = tomography.far_background_masks(made["none"]["delta"][p])
        for name in ("delta", "beta"):
            expected = tomography.corrected_slices(made["none"][name][p], name, "auto", far)
            np.testing.assert_allclose(made["auto"][name][p], expected, rtol=0, atol=1e-6 * np.abs(expected).max())
    np.testing.assert_array_equal(made["beta"]["delta"], made["none"]["delta"])
    np.testing.assert_array_equal(made["beta"]["beta"], made["quadratic"]["beta"])
    assert np.abs(made["quadratic"]["delta"] - made["none"]["delta"]).max() > 1e-3 * np.abs(made["none"]["delta"]).max()
    with pytest.raises(ValueError, match="unknown slice_background 'plane'") as exc:
        workflow.tomo_scan(path, slice_background="plane")
    assert "\n" not in str(exc.value)
    np.testing.assert_array_equal(xr.open_zarr(path)["delta"].values, made["auto"]["delta"])


def slice_quadratic(s):
    """The least-squares quadratic surface of one slice, on the slice's grid."""
    y, x = np.mgrid[: s.shape[0], : s.shape[1]] / max(s.shape)
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1).reshape(-1, 6)
    coef, *_ = np.linalg.lstsq(design, s.ravel(), rcond=None)
    return (design @ coef).reshape(s.shape)


@pytest.mark.gpu
def test_gpu_threads_are_capped_by_the_device_memory(cupy, tiny_scan, tmp_path, monkeypatch, capsys):
    """``--device gpu`` on the threaded scheduler runs no more tasks at once than fit in the
    GPU's free memory (estimate.retrieval_device_mb each), says so, and writes the store the
    uncapped run writes; the scheduler's own thread count is left as it was."""
    from pwf_dask.pipeline import estimate
    from pwf_dask.pipeline.cluster import Runner

    run = {**FAST, "angle_chain": 1}
    assert workflow._device_free_bytes(cupy) > 0
    wide, narrow = tmp_path / "wide.zarr", tmp_path / "narrow.zarr"
    with Runner("threads", workers=4) as runner:
        workflow.retrieve_scan(tiny_scan, wide, device="gpu", runner=runner, **run)
    task_mb = estimate.retrieval_device_mb((32, 64), 1.5, positions=2)  # tiny_scan's frame, the "auto" grid
    running, most = [0], [0]
    lock = threading.Lock()
    original = workflow._retrieve_task

    def counted(item, **kw):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        try:
            time.sleep(0.05)
            return original(item, **kw)
        finally:
            with lock:
                running[0] -= 1

    monkeypatch.setattr(workflow, "_retrieve_task", counted)
    monkeypatch.setattr(workflow, "_device_free_bytes", lambda xp: int(2.5 * task_mb * 1e6 / estimate.GPU_MEMORY_SHARE))
    capsys.readouterr()
    with Runner("threads", workers=4) as runner:
        workflow.retrieve_scan(tiny_scan, narrow, device="gpu", runner=runner, **run)
        assert runner.workers == 4
    assert "retrieve: 2 projections at a time on the GPU" in capsys.readouterr().err
    assert most[0] == 2
    for name in ("phase", "attenuation"):
        np.testing.assert_array_equal(xr.open_zarr(narrow)[name].values, xr.open_zarr(wide)[name].values)


def test_resume_computes_only_missing(tiny_scan, fast_recon, tmp_path, monkeypatch):
    full = tmp_path / "full.zarr"
    shutil.copytree(fast_recon, full)  # a whole run's store: its rerun below must add to it
    part = tmp_path / "part.zarr"
    original = workflow._retrieve_task
    started = []
    lock = threading.Lock()

    def killed_after_eight(item, **kw):
        with lock:
            started.append(item)
            n = len(started)
        if n > 8:
            raise KeyboardInterrupt("killed")
        return original(item, **kw)

    monkeypatch.setattr(workflow, "_retrieve_task", killed_after_eight)
    with pytest.raises(KeyboardInterrupt):
        workflow.retrieve_scan(tiny_scan, part, scheduler="threads", **FAST)
    time.sleep(3)  # tasks already running when the run died finish writing their own chunks
    monkeypatch.setattr(workflow, "_retrieve_task", original)
    done = zarr.open_group(str(part), mode="r", use_consolidated=False)["iterations"][...]
    assert 0 < (done >= 0).sum() < done.size
    res = workflow.retrieve_scan(tiny_scan, part, **FAST)
    assert res["computed"] == (done < 0).sum()
    stores_equal(full, part)
    # timings add up over the runs that filled a store (the killed run recorded none)
    a = dict(zarr.open_group(str(part), mode="r", use_consolidated=False).attrs)
    assert a["retrieval_tasks_timed"] == res["computed"] and a["retrieval_task_s_total"] > 0
    before = dict(zarr.open_group(str(full), mode="r", use_consolidated=False).attrs)
    assert before["retrieval_tasks_timed"] == done.size
    assert workflow.retrieve_scan(tiny_scan, full, **FAST)["computed"] == 0
    after = dict(zarr.open_group(str(full), mode="r", use_consolidated=False).attrs)
    assert after["retrieval_tasks_timed"] == done.size
    assert after["retrieval_wall_s_total"] == before["retrieval_wall_s_total"]
    # and each projection keeps its own task's time, whichever run made it
    seconds = zarr.open_group(str(part), mode="r", use_consolidated=False)["retrieval_seconds"][...]
    assert np.all(seconds > 0)


def test_the_diffuser_is_fitted_once_per_position_and_kept(tiny_scan, tmp_path, monkeypatch):
    """Issue #31: the diffuser fit is per-scan work, once per position (here 2 positions, 18
    projections) whatever the tasks and workers; a resumed run, even in a fresh worker, reads
    the stored fit instead of fitting again, and retrieves the same projections from it."""
    from pwf_dask import retrieval

    calls = []
    original = retrieval.estimate_diffuser

    def counted(*args, **kw):
        calls.append(kw.get("sample"))
        return original(*args, **kw)

    monkeypatch.setattr(retrieval, "estimate_diffuser", counted)
    workflow._DIFFUSERS.clear()
    recon = tmp_path / "r.zarr"
    workflow.retrieve_scan(tiny_scan, recon, **FAST)
    assert len(calls) == 2
    # the Wiener filters' floor reads the noise of the position's middle angle
    g, flat, dark, corrected = workflow._scan_frames(tiny_scan)
    middles = [workflow._read_corrected(g, "projections", (p, 4), flat, dark, corrected) for p in (0, 1)]
    assert any(all(np.array_equal(s, m) for s, m in zip(calls, order)) for order in (middles, middles[::-1]))
    g = zarr.open_group(str(recon), mode="r+", use_consolidated=False)
    assert (g.attrs["diffuser_model"], g.attrs["diffuser_model_chosen"]) == ("auto", "single-material")  # 10 keV
    for p in (0, 1):  # each on its own grid (the padding follows its coherence), NaN beyond it
        t = workflow._stored_diffuser(str(recon), p)
        assert np.isfinite(t).all() and t.shape[0] > 32 and t.shape[1] > 64
    before = g["phase"][0, :4]
    g["iterations"][0, :4] = -1
    workflow._DIFFUSERS.clear()
    workflow.retrieve_scan(tiny_scan, recon, **FAST)
    assert len(calls) == 2
    np.testing.assert_allclose(g["phase"][0, :4], before, rtol=1e-5, atol=1e-6)


def test_a_scan_chooses_each_positions_diffuser_model_once_by_the_probe(tiny_scan, tmp_path, monkeypatch):
    """Where "auto" probes (grains that hardly absorb: here a kappa of 1e-4 given), each
    position's model is chosen on its middle projection, recorded, and every projection of
    the position is retrieved with it: forced to switch, the store is the single-material
    run's; forced to stay, the zero-phase run's."""
    from pwf_dask import retrieval

    weak = dict(FAST, diffuser_beta_over_delta=1e-4)
    stores = {}
    runs = (
        ("switch", 1e9, "auto"),
        ("stay", 0.0, "auto"),
        ("single", None, "single-material"),
        ("zero", None, "zero-phase"),
    )
    for name, ratio, model in runs:
        if ratio is not None:
            monkeypatch.setattr(retrieval, "DIFFUSER_PROBE_RATIO", ratio)
        workflow._DIFFUSERS.clear()
        stores[name] = tmp_path / f"{name}.zarr"
        workflow.retrieve_scan(tiny_scan, stores[name], **weak, diffuser_model=model)
    g = zarr.open_group(str(stores["switch"]), mode="r", use_consolidated=False)
    assert json.loads(g.attrs["diffuser_model_per_position"]) == {"0": "single-material", "1": "single-material"}
    assert g.attrs["diffuser_model_chosen"] == "single-material"
    probe = json.loads(g.attrs["diffuser_probe_residual_pct"])
    assert set(probe) == {"0", "1"} and set(probe["0"]) == {"zero-phase", "single-material"}
    stay = zarr.open_group(str(stores["stay"]), mode="r", use_consolidated=False)
    assert stay.attrs["diffuser_model_chosen"] == "zero-phase"
    stores_equal(stores["switch"], stores["single"])
    stores_equal(stores["stay"], stores["zero"])
    single = zarr.open_group(str(stores["single"]), mode="r", use_consolidated=False)
    assert "diffuser_probe_residual_pct" not in single.attrs
    assert not np.allclose(stay["phase"][...], single["phase"][...], atol=1e-4)


def test_angle_chains_keep_halves_and_positions_apart():
    """Every projection once; each chain in angle order, every other angle, one position: the
    FSC's even/odd halves and positions never share a start. Length 1 is the paper's way."""
    angles = np.random.default_rng(0).permutation(np.linspace(0.0, 180.0, 23))
    chains = workflow.angle_chains(angles, 2, 4)
    items = [item for c in chains for item in c]
    assert sorted(items) == [(p, a) for p in range(2) for a in range(23)]
    rank = np.argsort(np.argsort(angles))  # index in angle order
    for c in chains:
        assert len(c) <= 4 and len({p for p, _ in c}) == 1
        ranks = [rank[a] for _, a in c]
        assert np.all(np.diff(ranks) == 2), ranks
    assert all(len(c) == 1 for c in workflow.angle_chains(angles, 1, 1))
    with pytest.raises(ValueError, match="angle_chain"):
        workflow.angle_chains(angles, 1, 0)


@pytest.mark.slow
def test_warm_started_chains_converge_to_the_same_projections_in_no_more_iterations(tiny_scan, tmp_path, capsys):
    """PWF started from the projection two angles before stops at the same phase as from zero
    (to a small part of the phase), in no more iterations, and the store records the chain
    length. One position of ``tiny_scan``'s scene (the chains are per position): measured
    0.98 of the cold iterations under the default stop (J or its data term, session 67; 0.84
    under J's test alone, session 65), the phases 1.3 % rms of the phase apart. On so small a
    frame the data term settles as soon from zero as from a neighbour; on the camera's whole
    frame a warm start takes 160 iterations for 300 (docs/validation.md)."""
    scan, cold, warm = tmp_path / "one.zarr", tmp_path / "cold.zarr", tmp_path / "warm.zarr"
    simulate_scan(scan, preset="demo", shape=(32, 64), angles=9, positions=1, seed=3, progress=False)
    workflow.retrieve_scan(scan, cold, angle_chain=1, max_iter=1000)
    workflow.retrieve_scan(scan, warm, angle_chain=5, max_iter=1000)
    c, w = xr.open_zarr(cold), xr.open_zarr(warm)
    assert (c.attrs["angle_chain"], w.attrs["angle_chain"]) == (1, 5)
    heads = np.zeros(c.iterations.shape, bool)
    for chain in workflow.angle_chains(c.angle.values, c.sizes["position"], 5):
        heads[chain[0]] = True
    np.testing.assert_array_equal(w.iterations.values[heads], c.iterations.values[heads])
    ratio = w.iterations.values[~heads].mean() / c.iterations.values[~heads].mean()
    assert ratio < 1.05, ratio
    scale = float(np.sqrt(np.mean(c.phase.values**2)))
    assert float(np.sqrt(np.mean((w.phase.values - c.phase.values) ** 2))) < 0.05 * scale
    assert cli.main(["retrieve", str(tiny_scan), str(tmp_path / "no.zarr"), "--angle-chain", "0"]) != 0
    assert "angle_chain is a number of projections >= 1" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "no.zarr").exists()


def test_a_chain_starts_from_the_solvers_psi_of_the_projection_before(tiny_scan, tmp_path, monkeypatch):
    """A warm start is PWF's own psi of the projection before (the stored result with the
    background planes added back), not the background-zeroed one: each start equals, to
    float32 rounding, the unzeroed psi of a projection retrieved earlier in the run."""
    from pwf_dask import retrieval
    from pwf_dask.physics.background import plane_from_terms

    original = retrieval.retrieve_projection
    solved, starts, lock = [], [], threading.Lock()

    def recording(sample, reference, **kw):
        res = original(sample, reference, **kw)
        planes = res.parameters["background_planes"]
        shape = np.shape(res.phase)
        psi = -(res.attenuation + plane_from_terms(planes["attenuation"], shape))
        psi = psi + 1j * (res.phase + plane_from_terms(planes["phase"], shape))
        with lock:
            solved.append((psi, -res.attenuation + 1j * res.phase))
            if not isinstance(kw.get("initial", "zero"), str):
                starts.append(np.asarray(kw["initial"]))
        return res

    monkeypatch.setattr(retrieval, "retrieve_projection", recording)
    recon = tmp_path / "r.zarr"
    workflow.retrieve_scan(tiny_scan, recon, angle_chain=3, **FAST)
    assert len(starts) == len(solved) - 2 * 2 * 2  # 2 positions x 2 halves x 2 chains start from zero
    for start in starts:
        misfit = [np.abs(start - psi).max() / np.abs(psi).max() for psi, _ in solved]
        k = int(np.argmin(misfit))
        assert misfit[k] < 1e-5
        assert np.abs(start - solved[k][1]).max() > 1e-3 * np.abs(solved[k][1]).max()  # not the zeroed one
    ds = xr.open_zarr(recon)
    assert ds["background_plane_phase"].dims == ("position", "angle", "plane_term")
    assert np.isfinite(ds["background_plane_phase"].values).all()


def test_resume_refuses_other_parameters(tiny_scan, fast_recon, tmp_path):
    recon = tmp_path / "r.zarr"
    shutil.copytree(fast_recon, recon)
    with pytest.raises(scan_io.ScanError, match="other parameters"):
        workflow.retrieve_scan(tiny_scan, recon, max_iter=30, tol=0.0)
    with pytest.raises(scan_io.ScanError, match="angle_chain"):
        workflow.retrieve_scan(tiny_scan, recon, angle_chain=1, **FAST)


def test_zingers_in_raw_counts_are_counted_per_projection(tiny_scan, tmp_path, capsys):
    """Saturated single pixels in one raw frame: left out there, counted in ``outlier_pixels``."""
    scan = tmp_path / "zingers.zarr"
    shutil.copytree(tiny_scan, scan)
    g = zarr.open_group(str(scan), mode="r+", use_consolidated=False)
    frame = g["projections"][1, 4]
    spots = [(3, 5), (10, 40), (20, 17), (31, 63)]
    for y, x in spots:
        frame[y, x] = np.iinfo(frame.dtype).max
    g["projections"][1, 4] = frame
    recon = tmp_path / "r.zarr"
    workflow.retrieve_scan(scan, recon, **FAST)
    counts = xr.open_zarr(recon)["outlier_pixels"].values
    assert counts[1, 4] == len(spots)
    counts[1, 4] = 0
    assert (counts == 0).all()
    assert cli.main(["retrieve", str(scan), str(tmp_path / "never.zarr"), "--outlier-sigma", "-1"]) != 0
    assert "outlier_sigma must be >= 0" in capsys.readouterr().err
    assert not (tmp_path / "never.zarr").exists()


def test_simulated_zingers_are_left_out_where_isolated(tmp_path):
    """``simulate --zingers``: the scan is the one without them except at the zingers (their own
    random stream), and every isolated zinger is found; two touching ones hide each other."""
    from scipy import ndimage

    clean, scan, recon = tmp_path / "c.zarr", tmp_path / "z.zarr", tmp_path / "r.zarr"
    argv = ["--preset", "demo", "--shape", "32", "64", "--angles", "3", "--positions", "1"]
    assert cli.main(["simulate", str(clean), *argv]) == 0
    assert cli.main(["simulate", str(scan), *argv, "--zingers", str(10 / (32 * 64))]) == 0
    hit = zarr.open_group(str(scan))["projections"][0] != zarr.open_group(str(clean))["projections"][0]
    assert (hit.sum(axis=(1, 2)) == 10).all()
    touching = np.stack([ndimage.convolve(h.astype(int), np.ones((3, 3), int), mode="constant") > 1 for h in hit])
    workflow.retrieve_scan(scan, recon, max_iter=5, tol=0.0)
    found = xr.open_zarr(recon)["outlier_pixels"].values[0]
    np.testing.assert_array_equal(found, (hit & ~touching).sum(axis=(1, 2)))


def _broken(src, dst, how):
    shutil.copytree(src, dst)
    g = zarr.open_group(str(dst), mode="r+", use_consolidated=False)
    if how == "no reference":
        del g["reference"]
    elif how == "no energy":
        del g.attrs["energy_eV"]
    elif how == "wrong dims":
        p = g["projections"][...]
        del g["projections"]
        scan_io.create_variable(
            g, "projections", p.shape[1:], (1,) + p.shape[2:], ("angle", "y", "x"), p.dtype, 0, p[0]
        )
    elif how == "reference shape":
        r = g["reference"][...][:, :-2]
        del g["reference"]
        scan_io.create_variable(g, "reference", r.shape, r.shape, ("position", "y", "x"), r.dtype, 0, r)
    elif how == "negative":
        g["projections"][0, 0, 0, 0] = 0  # below the dark level: negative after correction
    elif how == "distance":
        g.attrs["diffuser_detector_distance_m"] = -0.02
    elif how == "nan":
        f = g["flat"][...].astype("float32")
        del g["flat"]
        f[3, 3] = np.nan
        scan_io.create_variable(g, "flat", f.shape, f.shape, ("y", "x"), "float32", 0, f)
    scan_io.consolidate(dst)
    return dst


@pytest.mark.parametrize(
    "how,message",
    [
        ("no reference", "missing variable 'reference'"),
        ("no energy", "missing attribute 'energy_eV'"),
        ("wrong dims", "expected (position, angle, y, x)"),
        ("reference shape", "does not match"),
        ("negative", "negative values"),
        ("distance", "diffuser_detector_distance_m"),
        ("nan", "non-finite"),
    ],
)
def test_bad_scans_exit_nonzero_with_one_line_and_write_nothing(tiny_scan, tmp_path, capsys, how, message):
    bad = _broken(tiny_scan, tmp_path / "bad.zarr", how)
    recon = tmp_path / "never.zarr"
    rc = cli.main(["retrieve", str(bad), str(recon)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0
    assert message in err[-1] and len([e for e in err if "error" in e]) == 1
    assert not recon.exists()


def test_a_recorded_upstream_distance_is_used_recorded_and_kept_on_resume(tiny_scan, tmp_path, capsys):
    """The optional scan attribute ``diffuser_upstream_m`` reaches PWF and the store's
    attributes; a resume with another distance is refused; on an L1 > 0 scan it is refused."""
    import zarr

    scan, recon = tmp_path / "up.zarr", tmp_path / "r.zarr"
    argv = ["simulate", str(scan), "--preset", "demo", "--shape", "32", "64", "--angles", "3", "--positions", "1"]
    assert cli.main([*argv, "--diffuser-upstream-m", "5e-3"]) == 0
    zarr.open_group(str(scan), mode="r+").attrs["diffuser_upstream_m"] = 5e-3
    scan_io.consolidate(scan)
    workflow.retrieve_scan(scan, recon, **FAST)
    assert xr.open_zarr(recon).attrs["diffuser_upstream_m"] == 5e-3
    capsys.readouterr()
    assert (
        cli.main(["retrieve", str(scan), str(recon), "--max-iter", "25", "--tol", "0", "--diffuser-upstream-m", "0"])
        != 0
    )
    # the distance enters the coherence calibration too (the templates' propagation distance)
    refusal = capsys.readouterr().err.strip().splitlines()[-1]
    assert "exists with other parameters (" in refusal and "diffuser_upstream_m)" in refusal
    assert cli.main(["retrieve", str(tiny_scan), str(tmp_path / "no.zarr"), "--diffuser-upstream-m", "5e-3"]) != 0
    assert "needs sample_diffuser_distance_m = 0" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "no.zarr").exists()
    zarr.open_group(str(scan), mode="r+").attrs["diffuser_upstream_m"] = -1e-3
    scan_io.consolidate(scan)
    assert cli.main(["retrieve", str(scan), str(tmp_path / "no.zarr")]) != 0
    assert "diffuser_upstream_m must be >= 0" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "no.zarr").exists()


def test_simulate_with_the_diffuser_upstream_records_l1_zero(tmp_path):
    scan = tmp_path / "up.zarr"
    argv = ["simulate", str(scan), "--preset", "demo", "--shape", "32", "64", "--angles", "2", "--positions", "1"]
    assert cli.main([*argv, "--diffuser-upstream-m", "5e-3"]) == 0
    ds = xr.open_zarr(scan)
    assert ds.attrs["sample_diffuser_distance_m"] == 0.0
    assert ds.attrs["simulation_diffuser_upstream_m"] == 5e-3
    assert scan_io.open_scan(scan) is not None  # a valid CONTRACT §1 scan


def test_simulate_at_another_beamline_records_its_optics_and_scales_the_sample(tmp_path):
    """``simulate --energy-eV --pixel-size-m --...-distance-m --coherence-length-*-m``: the paper's
    values given are the default bit for bit; others are recorded as the contract's attributes
    (the lengths only as the truth), the phantom is drawn in metres from the frame (twice the
    pixel, twice the cylinder), and a coarser coherence blurs the reference's speckle."""
    args = ["--preset", "demo", "--shape", "32", "64", "--angles", "2", "--positions", "1", "--corrected"]
    paper = ["--energy-eV", "10000", "--pixel-size-m", "0.65e-6", "--sample-diffuser-distance-m", "3e-3"]
    paper += ["--diffuser-detector-distance-m", "0.02", "--coherence-length-x-m", "3.47e-6"]
    other = ["--energy-eV", "20000", "--pixel-size-m", "1.3e-6", "--sample-diffuser-distance-m", "0"]
    other += ["--diffuser-upstream-m", "0.05", "--diffuser-detector-distance-m", "0.1"]
    blurred = ["--coherence-length-x-m", "12e-6", "--coherence-length-y-m", "12e-6"]
    for name, extra in (("a", []), ("p", paper), ("o", other), ("b", blurred)):
        assert cli.main(["simulate", str(tmp_path / f"{name}.zarr"), *args, *extra]) == 0
    a, p, o, b = (xr.open_zarr(tmp_path / f"{n}.zarr") for n in "apob")
    np.testing.assert_array_equal(a.projections.values, p.projections.values)
    assert o.attrs["energy_eV"] == 20000 and o.attrs["pixel_size_m"] == 1.3e-6
    assert o.attrs["sample_diffuser_distance_m"] == 0 and o.attrs["diffuser_detector_distance_m"] == 0.1
    assert float(o.x[1] - o.x[0]) == pytest.approx(1.3e-6)
    assert "coherence_length_x_m" not in b.attrs  # a user's scan calibrates them
    assert b.attrs["simulation_coherence_length_x_m"] == 12e-6
    radius = {n: phantom_from_json(d.attrs["simulation_phantom"]).cylinder_radius_m for n, d in (("a", a), ("o", o))}
    assert radius["o"] == pytest.approx(2 * radius["a"])
    assert b.reference.values.std() < 0.8 * a.reference.values.std()


def test_simulate_with_an_extended_source_records_it_and_moves_only_the_sample_frames(tmp_path):
    """``simulate --coherence-model source``: recorded as the truth; the references are the
    paper's blur bit for bit, the projections differ (the sample moves against the speckle)."""
    args = ["--preset", "demo", "--shape", "32", "64", "--angles", "2", "--positions", "1", "--corrected"]
    up = ["--diffuser-upstream-m", "0.02"]
    assert cli.main(["simulate", str(tmp_path / "d.zarr"), *args, *up]) == 0
    assert cli.main(["simulate", str(tmp_path / "s.zarr"), *args, *up, "--coherence-model", "source"]) == 0
    d, s = xr.open_zarr(tmp_path / "d.zarr"), xr.open_zarr(tmp_path / "s.zarr")
    assert d.attrs["simulation_coherence_model"] == "detector" and s.attrs["simulation_coherence_model"] == "source"
    assert "coherence_model" not in s.attrs  # the truth only, as the lengths
    np.testing.assert_array_equal(d.reference.values, s.reference.values)
    assert not np.array_equal(d.projections.values, s.projections.values)
    rel = np.abs(s.projections.values - d.projections.values).mean() / d.projections.values.mean()
    assert 1e-3 < rel < 0.1


@pytest.mark.parametrize("photons", [1e4, 1e6])
def test_simulated_raw_counts_fit_sixteen_bits_at_any_dose(tmp_path, photons):
    """Raw uint16 counts: at 1e4 ph/px one photon is one count; above 1.6e4 a count stands for
    several photons, so the flat keeps below 65535 (at 1e5 it wrapped and 76 % of the frames
    clipped). Flat/dark-corrected, the raw reference is the corrected scan's reference (the same
    speckle) within both scans' photon noise."""
    raw, corrected = tmp_path / "raw.zarr", tmp_path / "corrected.zarr"
    scene = dict(preset="demo", shape=(48, 64), angles=2, positions=1, photons=photons, progress=False)
    simulate_scan(raw, **scene)
    simulate_scan(corrected, raw=False, **scene)
    ds = xr.open_zarr(raw)
    per_count = ds.attrs["simulation_photons_per_count"]
    assert per_count == max(1.0, photons / 16_000)
    flat, dark = ds.flat.values.astype(float), ds.dark.values.astype(float)
    np.testing.assert_allclose((flat - dark).max() * per_count, photons, rtol=1e-3)
    for frame in (ds.reference.values[0], ds.projections.values[0, 0]):
        assert np.mean(frame == 65535) < 1e-3
    reference = (ds.reference.values[0] - dark) / (flat - dark)
    truth = xr.open_zarr(corrected).reference.values[0].astype(float)
    difference = reference / reference.mean() - truth / truth.mean()
    assert np.sqrt(np.mean(difference**2)) < 3 * np.sqrt(2 / photons)


def test_raw_counts_at_full_scale_are_left_out_of_the_fit_and_reported_once(tmp_path, monkeypatch, caplog):
    """Raw uint16 counts at 65535 are saturated: PWF's task passes them as ``bad_pixels``, and
    the run says so in one line, however many frames have them."""
    from pwf_dask import retrieval
    from pwf_dask.physics.detector import saturated_pixels

    scan, recon = tmp_path / "scan.zarr", tmp_path / "recon.zarr"
    simulate_scan(scan, preset="demo", shape=(32, 64), angles=3, positions=1, seed=1, progress=False)
    g = zarr.open_group(str(scan), mode="r+")
    frames = g["projections"][...]
    frames[0, :, 10:12, 20:23] = 65535  # a bright spot clipped in every frame
    g["projections"][...] = frames
    assert saturated_pixels(frames[0, 1]).sum() == 6
    assert saturated_pixels(frames[0, 1].astype(np.float32)) is None  # full scale unknown
    passed = []
    original = retrieval.retrieve_projection

    def spy(*args, **kwargs):
        passed.append(kwargs.get("bad_pixels"))
        return original(*args, **kwargs)

    monkeypatch.setattr(retrieval, "retrieve_projection", spy)
    with caplog.at_level(logging.WARNING, logger="pwf_dask.pipeline.workflow"):
        workflow.retrieve_scan(scan, recon, **FAST)
    assert len(passed) == 3 and all(int(b.sum()) == 6 and bool(b[10:12, 20:23].all()) for b in passed)
    said = [r.getMessage() for r in caplog.records if "saturated" in r.getMessage()]
    assert len(said) == 1 and "6 pixels of projection" in said[0]


@pytest.mark.parametrize("shape", [(32, 256), (33, 200)])
def test_simulate_a_slab_of_few_rows(tmp_path, shape):
    """A wide frame of few rows (a slab of a detector) holds beads that fit its height (the
    placement failed with 'high - low < 0' before)."""
    scan = tmp_path / "slab.zarr"
    argv = ["simulate", str(scan), "--preset", "demo", "--shape", *map(str, shape), "--angles", "2", "--positions", "1"]
    assert cli.main(argv) == 0
    ph = phantom_from_json(xr.open_zarr(scan).attrs["simulation_phantom"])
    height = shape[0] * xr.open_zarr(scan).attrs["pixel_size_m"]
    assert len(ph.spheres) >= 3
    assert all(abs(sp.y_m) + sp.radius_m <= 0.5 * height for sp in ph.spheres)


def test_simulate_without_beads_holds_the_cylinder_alone(tmp_path):
    """``--no-beads``: the same scan's phantom without its glass spheres (one material), the
    cylinder and the diffuser unchanged; the frames differ only where beads were."""
    argv = ["--preset", "demo", "--shape", "32", "64", "--angles", "2", "--positions", "1", "--corrected"]
    with_beads, without = tmp_path / "b.zarr", tmp_path / "nb.zarr"
    assert cli.main(["simulate", str(with_beads), *argv]) == 0
    assert cli.main(["simulate", str(without), *argv, "--no-beads"]) == 0
    a, b = xr.open_zarr(with_beads), xr.open_zarr(without)
    pa, pb = (phantom_from_json(d.attrs["simulation_phantom"]) for d in (a, b))
    assert len(pa.spheres) >= 3 and pb.spheres == ()
    assert pb.cylinder_radius_m == pa.cylinder_radius_m
    np.testing.assert_array_equal(a.reference.values, b.reference.values)
    assert not np.array_equal(a.projections.values, b.projections.values)


def test_mist_scan_combines_four_positions_and_records_its_material(tiny_scan, tmp_path, capsys):
    assert cli.main(["retrieve", str(tiny_scan), str(tmp_path / "no.zarr"), "--method", "mist"]) != 0
    assert "mist needs K >= 4" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "no.zarr").exists()
    scan, recon = tmp_path / "k4.zarr", tmp_path / "mist.zarr"
    simulate_scan(scan, preset="demo", shape=(32, 64), angles=5, positions=4, seed=3, progress=False)
    argv = ["run", str(scan), str(recon), "--method", "mist", "--sample-material", "PMMA"]
    assert cli.main(argv) == 0
    ds = xr.open_zarr(recon)
    assert ds.sizes["position"] == 1 and ds.attrs["method"] == "mist"
    delta, beta = delta_beta("PMMA", ds.attrs["energy_eV"])
    assert ds.attrs["sample_material"] == "PMMA"
    assert ds.attrs["sample_delta_over_beta"] == pytest.approx(delta / beta)
    assert np.isfinite(ds["delta"].values).all()


def test_single_material_prior_is_recorded_and_kept_on_resume(tiny_scan, fast_recon, tmp_path, capsys):
    """``--single-material`` reaches PWF with the sample's delta/beta, the store records both,
    a resume without it is refused, and a bad ratio is refused before anything is written."""
    recon = tmp_path / "sm.zarr"
    fast = ["--max-iter", "25", "--tol", "0"]
    argv = ["retrieve", str(tiny_scan), str(recon), *fast, "--single-material", "--sample-material", "PMMA"]
    assert cli.main(argv) == 0
    ds = xr.open_zarr(recon)
    delta, beta = delta_beta("PMMA", ds.attrs["energy_eV"])
    assert ds.attrs["single_material"] is True and ds.attrs["sample_material"] == "PMMA"
    assert ds.attrs["sample_delta_over_beta"] == pytest.approx(delta / beta)
    capsys.readouterr()
    assert cli.main(["retrieve", str(tiny_scan), str(recon), *fast]) != 0
    assert "other parameters (single_material" in capsys.readouterr().err.strip().splitlines()[-1]
    plain = xr.open_zarr(fast_recon)
    assert plain.attrs["single_material"] is False
    assert not np.array_equal(ds.phase.values, plain.phase.values)
    bad = ["retrieve", str(tiny_scan), str(tmp_path / "no.zarr"), "--single-material", "--sample-delta-over-beta", "-5"]
    assert cli.main(bad) != 0
    assert "sample_delta_over_beta must be positive" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "no.zarr").exists()
    assert cli.main(["retrieve", str(tiny_scan), str(tmp_path / "no.zarr"), "--method", "umpa", "--single-material"])
    assert "single_material applies to method 'pwf', not 'umpa'" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "no.zarr").exists()


def test_stages_in_wrong_order_are_refused(tmp_path, capsys):
    assert cli.main(["tomo", str(tmp_path / "none.zarr")]) != 0
    assert "no such reconstruction" in capsys.readouterr().err


def test_a_drifting_diffuser_is_measured_per_projection(tmp_path, capsys):
    """``simulate --diffuser-drift-px``: the diffuser creeps linearly over the scan; every
    projection's drift is recorded (PWF moves its t_r by it), and a bad value is refused."""
    scan, recon = tmp_path / "drift.zarr", tmp_path / "r.zarr"
    args = ["simulate", str(scan), "--preset", "demo", "--shape", "64", "96", "--angles", "5", "--positions", "1"]
    args += ["--grain-radius-um", "1.2"]  # ten P3000 grains across 64 x 96 scatter the estimate by 0.1 px
    assert cli.main([*args, "--seed", "3", "--diffuser-drift-px", "0.4", "-1.2"]) == 0
    assert cli.main(["retrieve", str(scan), str(tmp_path / "never.zarr"), "--diffuser-drift", "sideways"]) != 0
    assert "diffuser_drift must be" in capsys.readouterr().err
    assert not (tmp_path / "never.zarr").exists()
    workflow.retrieve_scan(scan, recon, **FAST)
    ds = xr.open_zarr(recon)
    assert (ds.attrs["simulation_diffuser_drift_y_px"], ds.attrs["simulation_diffuser_drift_x_px"]) == (0.4, -1.2)
    steps = np.linspace(0.0, 1.0, 5)
    np.testing.assert_allclose(ds["diffuser_drift_y_px"].values[0], 0.4 * steps, atol=0.05)
    np.testing.assert_allclose(ds["diffuser_drift_x_px"].values[0], -1.2 * steps, atol=0.05)


def test_simulated_dark_field_blurs_the_speckle_behind_the_sample_only(tmp_path):
    """``simulate --dark-field-px``: behind the sample the speckle loses contrast, beside it
    it keeps it, and the reference is untouched (noise-free: test_stability)."""
    args = ["--preset", "demo", "--shape", "48", "96", "--angles", "2", "--positions", "1", "--corrected"]
    args += ["--seed", "4"]
    assert cli.main(["simulate", str(tmp_path / "a.zarr"), *args]) == 0
    assert cli.main(["simulate", str(tmp_path / "b.zarr"), *args, "--dark-field-px", "2"]) == 0
    a, b = xr.open_zarr(tmp_path / "a.zarr"), xr.open_zarr(tmp_path / "b.zarr")
    assert b.attrs["simulation_dark_field_px"] == 2.0
    np.testing.assert_array_equal(a.reference.values, b.reference.values)
    pa, pb = a.projections.values[0], b.projections.values[0]
    side = slice(0, 12)  # the cylinder spans the middle 0.58 of the width
    assert pb[..., side].std() == pytest.approx(pa[..., side].std(), rel=0.05)
    middle = slice(40, 56)
    assert pb[..., middle].std() < 0.8 * pa[..., middle].std()
    assert pb[..., middle].mean() == pytest.approx(pa[..., middle].mean(), rel=0.02)


def test_simulated_detector_blur_is_recorded_and_keeps_the_light(tmp_path):
    """``simulate --detector-blur-um --detector-halo``: the detector's PSF lowers the speckle's
    contrast in every frame and keeps its light; the truth is recorded; none named is none. PWF
    told the halo (``detector_halo_*``) fits the scan's diffuser with it and records it."""
    args = ["--preset", "demo", "--shape", "48", "96", "--angles", "2", "--positions", "1", "--corrected"]
    args += ["--seed", "4"]
    assert cli.main(["simulate", str(tmp_path / "a.zarr"), *args]) == 0
    assert cli.main(["simulate", str(tmp_path / "z.zarr"), *args, "--detector-blur-um", "0"]) == 0
    blur = ["--detector-blur-um", "1.5", "--detector-halo", "0.2", "5"]
    assert cli.main(["simulate", str(tmp_path / "b.zarr"), *args, *blur]) == 0
    a, z, b = (xr.open_zarr(tmp_path / f"{n}.zarr") for n in "azb")
    np.testing.assert_array_equal(a.reference.values, z.reference.values)
    assert b.attrs["simulation_detector_blur_fwhm_m"] == pytest.approx(1.5e-6)
    assert b.attrs["simulation_detector_halo_fraction"] == 0.2
    assert b.attrs["simulation_detector_halo_radius_m"] == pytest.approx(5e-6)
    for frames in ("reference", "projections"):
        pa, pb = a[frames].values, b[frames].values
        assert pb.std() < 0.9 * pa.std()
        assert pb.mean() == pytest.approx(pa.mean(), rel=0.01)
    # PWF told the halo: the scan's diffuser is estimated with it, and the store records it
    told = {"detector_halo_fraction": 0.2, "detector_halo_radius_m": 5e-6}
    workflow.retrieve_scan(tmp_path / "b.zarr", tmp_path / "plain.zarr", **FAST)
    workflow.retrieve_scan(tmp_path / "b.zarr", tmp_path / "told.zarr", **told, **FAST)
    plain, with_halo = xr.open_zarr(tmp_path / "plain.zarr"), xr.open_zarr(tmp_path / "told.zarr")
    assert with_halo.attrs["detector_halo_fraction"] == 0.2 and "detector_halo_fraction" not in plain.attrs
    assert not np.allclose(with_halo["diffuser"].values, plain["diffuser"].values, equal_nan=True)


def test_discrepancy_alpha_is_chosen_once_recorded_and_kept_on_resume(tiny_scan, tmp_path, capsys):
    """``--alpha discrepancy``: Im(alpha) chosen on one projection (position 0, middle angle),
    used for every projection, recorded with the rungs tried; a resumed run keeps it."""
    recon = tmp_path / "r.zarr"
    workflow.retrieve_scan(tiny_scan, recon, alpha="discrepancy", **FAST)
    assert "by the discrepancy principle on projection (0, 4)" in capsys.readouterr().err
    attrs = xr.open_zarr(recon).attrs
    trials = json.loads(attrs["alpha_trials"])
    assert attrs["alpha_rule"] == "discrepancy" and len(trials) >= 2
    assert attrs["phase_sensitivity"] > 0.015  # measured for every PWF scan, the warning reads it
    assert complex(attrs["alpha"]).imag in solver.ALPHA_IMAG_LADDER and complex(attrs["alpha"]).real == 0.1
    assert attrs["alpha"] in [t[0] for t in trials]
    workflow.retrieve_scan(tiny_scan, recon, alpha="discrepancy", **FAST)  # resumed: same parameters
    assert "discrepancy principle" not in capsys.readouterr().err


def test_sensitivity_alpha_is_one_for_the_scan_and_recorded(tiny_scan, tmp_path, capsys):
    """``--alpha sensitivity``: one alpha for every projection, from the phase sensitivity
    averaged over the positions' references, recorded with it; a resumed run finds the same."""
    recon = tmp_path / "r.zarr"
    workflow.retrieve_scan(tiny_scan, recon, alpha="sensitivity", **FAST)
    assert "for the data's phase sensitivity" in capsys.readouterr().err
    attrs = xr.open_zarr(recon).attrs
    s, contrast = attrs["phase_sensitivity"], attrs["attenuation_contrast"]
    assert attrs["alpha_rule"] == "sensitivity" and s > 0 and 0 < contrast < solver.TUNED_ATTENUATION_CONTRAST
    assert attrs["phase_sensitivity_noise_bound"] == "n/a"  # measured only where S reads none
    assert attrs["alpha"] == str(solver.sensitivity_alpha(s, attenuation_contrast=contrast)).strip("()")
    workflow.retrieve_scan(tiny_scan, recon, alpha="sensitivity", **FAST)  # resumed: same parameters
    assert xr.open_zarr(recon).attrs["alpha"] == attrs["alpha"]


def test_a_scan_whose_references_read_no_sensitivity_takes_their_noise_bound(tiny_scan, tmp_path, monkeypatch, capsys):
    """Where every position's reference reads S = 0 (forced here), the scan measures the noise
    bound of each (the mean is recorded) and, from NOISE_HIDDEN_SENSITIVITY up, sets Im(alpha)
    from it and says so; below, the floor's alpha stays."""
    monkeypatch.setattr(workflow.calibration, "phase_sensitivity", lambda *a: 0.0)
    for bound in (3e-3, 0.5 * solver.NOISE_HIDDEN_SENSITIVITY):
        monkeypatch.setattr(workflow.calibration, "phase_sensitivity_noise_bound", lambda *a, b=bound: b)
        recon = tmp_path / f"{bound}.zarr"
        workflow.retrieve_scan(tiny_scan, recon, alpha="sensitivity", **FAST)
        attrs = xr.open_zarr(recon).attrs
        assert attrs["phase_sensitivity"] == 0.0 and attrs["phase_sensitivity_noise_bound"] == bound
        taken = solver.rule_sensitivity(0.0, bound)
        assert complex(attrs["alpha"]) == solver.sensitivity_alpha(
            taken, attenuation_contrast=attrs["attenuation_contrast"]
        )
        said = "none above the photon noise" in capsys.readouterr().err
        assert said == (bound >= solver.NOISE_HIDDEN_SENSITIVITY)


def test_a_strongly_absorbing_scan_lowers_one_re_alpha_for_every_projection(tiny_scan, tmp_path, monkeypatch, capsys):
    """The scan's attenuation contrast, the largest of position 0's projections at 0, 1/3 and 2/3
    of the angles, sets Re(alpha) once (twice the tuned contrast here: a quarter of 0.1), says
    so and records it; a given alpha measures nothing."""
    reads = []
    measure = workflow.calibration.attenuation_contrast
    monkeypatch.setattr(
        workflow.calibration, "attenuation_contrast", lambda *a: reads.append(a[0].shape) or 2 * measure(*a)
    )
    contrast = workflow.scan_attenuation_contrast(*workflow._scan_frames(tiny_scan), None)
    assert len(reads) == 3
    monkeypatch.setattr(workflow, "scan_attenuation_contrast", lambda *a: 2 * solver.TUNED_ATTENUATION_CONTRAST)
    recon = tmp_path / "r.zarr"
    workflow.retrieve_scan(tiny_scan, recon, alpha="sensitivity", **FAST)
    attrs = xr.open_zarr(recon).attrs
    twice = 2 * solver.TUNED_ATTENUATION_CONTRAST
    assert complex(attrs["alpha"]).real == pytest.approx(0.025) and attrs["attenuation_contrast"] == twice
    assert f"and the sample's attenuation contrast {twice:.3g} (Re(alpha) lowered)" in capsys.readouterr().err
    given = tmp_path / "given.zarr"
    workflow.retrieve_scan(tiny_scan, given, alpha=0.1 + 0.05j, **FAST)
    assert xr.open_zarr(given).attrs["attenuation_contrast"] == "n/a" and contrast > 0


def test_a_scan_checks_the_alpha_rules_lower_alpha_once_against_the_diffuser_models(
    tiny_scan, tmp_path, monkeypatch, capsys
):
    """Where the rule lowers alpha (the scan's sensitivity set to 1e-4 here) and the diffuser is
    the single-material fit, the scan probes both models once, on position 0's middle
    projection, records their residual ratio and keeps the default alpha where the fit misfits
    more (forced each way here through the bound); a resumed run reads the ratio back and probes
    nothing; zero phase is never probed. Under "auto", which took the fit by the grains'
    absorption, the fit gives way instead: zero phase at the rule's alpha, on every position and
    again on resume; a store made under "auto" at the default alpha (before session 101) resumes
    as made."""
    from pwf_dask import retrieval

    monkeypatch.setattr(workflow, "scan_phase_sensitivity", lambda *a, **k: 1e-4)
    calls = []
    probe = retrieval.probe_diffuser_models
    monkeypatch.setattr(retrieval, "probe_diffuser_models", lambda *a, **k: calls.append(a) or probe(*a, **k))
    lowered = str(solver.sensitivity_alpha(1e-4)).strip("()")
    single = dict(FAST, alpha="sensitivity", diffuser_model="single-material")
    for bound, alpha in ((0.0, "0.1+0.05j"), (1e9, lowered)):
        monkeypatch.setattr(retrieval, "ALPHA_RULE_MAX_MODEL_RATIO", bound)
        workflow._DIFFUSERS.clear()
        recon = tmp_path / f"{bound}.zarr"
        workflow.retrieve_scan(tiny_scan, recon, **single)
        attrs = xr.open_zarr(recon).attrs
        assert attrs["alpha"] == alpha and attrs["alpha_rule_model_ratio"] > 0
    said = capsys.readouterr().err
    assert "the default, not lowered, as the single-material diffuser fit misfits" in said
    assert f"alpha: {lowered} for" in said and "x zero phase's" in said
    assert len(calls) == 2 and calls[0][0].shape == (32, 64)
    workflow.retrieve_scan(tiny_scan, recon, **single)  # resumed: the stored ratio
    assert len(calls) == 2
    made_before = zarr.open_group(str(recon), mode="r+", use_consolidated=False)
    del made_before.attrs["alpha_rule_model_ratio"]  # a store of the rule before the probe
    monkeypatch.setattr(retrieval, "ALPHA_RULE_MAX_MODEL_RATIO", 0.0)
    workflow.retrieve_scan(tiny_scan, recon, **single)  # resumes with its own alpha, unprobed
    assert len(calls) == 2 and xr.open_zarr(recon).attrs["alpha"] == lowered
    zero = tmp_path / "zero.zarr"
    workflow.retrieve_scan(tiny_scan, zero, **dict(single, diffuser_model="zero-phase"))
    attrs = xr.open_zarr(zero).attrs
    assert len(calls) == 2 and attrs["alpha_rule_model_ratio"] == "n/a" and attrs["alpha"] == lowered
    # "auto" that took the fit by its absorption (kappa 0.5 here) gives the fit up, not the alpha
    auto = tmp_path / "auto.zarr"
    absorbing = dict(single, diffuser_model="auto", diffuser_beta_over_delta=0.5)
    for _ in range(2):  # the second resumes: the stored ratio, the same choice
        workflow._DIFFUSERS.clear()
        workflow.retrieve_scan(tiny_scan, auto, **absorbing)
        attrs = xr.open_zarr(auto).attrs
        assert attrs["alpha"] == lowered and attrs["diffuser_model_chosen"] == "zero-phase"
        assert json.loads(attrs["diffuser_model_per_position"]) == {"0": "zero-phase", "1": "zero-phase"}
    assert len(calls) == 3
    assert "with the zero-phase diffuser: the single-material fit misfits" in capsys.readouterr().err
    made_before = zarr.open_group(str(auto), mode="r+", use_consolidated=False)
    made_before.attrs["alpha"] = "0.1+0.05j"  # "auto" at the default alpha, before session 101
    made = json.loads(made_before.attrs["pwf_dask_parameters"])
    made_before.attrs["pwf_dask_parameters"] = json.dumps({**made, "alpha": "0.1+0.05j"})
    workflow.retrieve_scan(tiny_scan, auto, **absorbing)  # resumes as made, unprobed
    assert len(calls) == 3 and xr.open_zarr(auto).attrs["alpha"] == "0.1+0.05j"


def test_the_store_records_the_diffuser_model_auto_chose():
    """``diffuser_model="auto"``: the single-material fit at 10 keV, zero phase at 20 keV (silicon
    carbide's beta/delta 0.003), a named model as named, an unknown one refused in one line."""
    assert workflow._model_record("pwf", {}, 10e3)["diffuser_model_chosen"] == "single-material"
    assert workflow._model_record("pwf", {}, 20e3)["diffuser_model_chosen"] == "zero-phase"
    named = workflow._model_record("pwf", {"diffuser_model": "single-material"}, 20e3)
    assert named["diffuser_model"] == named["diffuser_model_chosen"] == "single-material"
    assert "diffuser_model_chosen" not in workflow._model_record("lcs", {}, 20e3)
    with pytest.raises(ValueError, match="unknown diffuser_model 'random'"):
        workflow._model_record("pwf", {"diffuser_model": "random"}, 10e3)
