"""`pwf-dask estimate`: memory and time per stage, predicted from a scan's metadata (issue #29)."""

import numpy as np
import pytest

from pwf_dask import cli
from pwf_dask.pipeline import estimate
from pwf_dask.stores import scan_io

SPEEDS = estimate.Speeds(iteration_s=0.16, fft_s=0.01, fbp_row_s=0.05, fbp_row_s_per_angle=1e-3)


def _metadata_scan(path, shape=(2160, 2560), angles=801, positions=1):
    """A scan store of the paper's size holding only its metadata (no frame is written)."""
    attrs = {
        "energy_eV": 1e4,
        "pixel_size_m": 0.65e-6,
        "sample_diffuser_distance_m": 3e-3,
        "diffuser_detector_distance_m": 0.02,
        "flat_dark_corrected": True,
    }
    scan_io.create_scan(
        path,
        n_positions=positions,
        angles_deg=np.linspace(0, 180, angles),
        shape=shape,
        pixel_size_m=0.65e-6,
        dtype="uint16",
        attrs=attrs,
    )
    scan_io.consolidate(path)
    return path


def test_memory_grows_with_what_each_task_holds():
    base = estimate.estimate_scan((512, 512), 181, 2, speeds=SPEEDS)
    wide = estimate.estimate_scan((512, 1024), 181, 2, speeds=SPEEDS)
    retrieve, tomo, fsc = (s.peak_mb_per_worker - estimate.WORKER_BASE_MB for s in base)
    retrieve2, tomo2, fsc2 = (s.peak_mb_per_worker - estimate.WORKER_BASE_MB for s in wide)
    # retrieval: the padded grid (~2x pixels); FSC: voxels of a slice grow as nx^2
    assert 1.8 < (retrieve2 - estimate.RETRIEVAL_BASE_MB) / (retrieve - estimate.RETRIEVAL_BASE_MB) < 2.1
    assert fsc2 / fsc == pytest.approx(4.0)
    finer = estimate.estimate_scan((512, 512), 181, 2, field_upsample=2, speeds=SPEEDS)
    assert finer[0].peak_mb_per_worker > base[0].peak_mb_per_worker
    assert tomo2 > tomo


def test_time_divides_over_workers_and_counts_every_projection():
    one = estimate.estimate_scan((256, 256), 100, 2, workers=1, iterations=200, speeds=SPEEDS)
    eight = estimate.estimate_scan((256, 256), 100, 2, workers=8, iterations=200, speeds=SPEEDS)
    assert one[0].tasks == 200 and one[0].seconds == pytest.approx(200 * 200 * 0.16)
    assert eight[0].seconds == pytest.approx(one[0].seconds / 8)
    assert one[1].seconds == pytest.approx(2 * (0.05 + 1e-3 * 100) * 256 * 2)


def test_estimate_command_prints_each_stage_and_warns_when_a_stage_cannot_fit(tmp_path, capsys, monkeypatch):
    """The paper's scan fits a 24 GB workstation: its FSC compares the central 64 rows (whole
    2160 x 2560^2 tomograms would need ~0.8 TB). On an 8 GB laptop it does not, which the
    estimate says before anything runs."""
    scan = _metadata_scan(tmp_path / "paper.zarr")
    monkeypatch.setattr(estimate, "iteration_seconds", lambda *args: 1.4)  # a full frame's is timed below
    monkeypatch.setattr(estimate, "machine_memory_mb", lambda: 24e3)
    assert cli.main(["estimate", str(scan), "--workers", "8"]) == 0
    out = capsys.readouterr().out
    for stage in ("retrieve", "tomo", "fsc"):
        assert f"\n{stage}" in out
    assert "801 angles x 2160 x 2560" in out and "central 64 rows" in out
    assert "warning" not in out
    # a full frame's retrieval on a GPU, planned on the 1.5x grid: 4.2 GB measured on an H100
    task_gb = estimate.retrieval_device_mb((2160, 2560), estimate.DEFAULT_FIELD_UPSAMPLE) / 1e3
    assert 4.0 < task_gb < 5.0
    assert f"{task_gb:.1f} GB of device memory per task" in out and "on 24 GB" in out
    monkeypatch.setattr(estimate, "machine_memory_mb", lambda: 8e3)
    assert cli.main(["estimate", str(scan), "--workers", "8"]) == 0
    assert "warning: fsc needs" in capsys.readouterr().out


def test_estimate_refuses_bad_numbers(tmp_path, capsys):
    scan = _metadata_scan(tmp_path / "s.zarr", shape=(64, 64), angles=10)
    assert cli.main(["estimate", str(scan), "--workers", "0"]) == 2
    assert "--workers" in capsys.readouterr().err


def test_the_iteration_is_timed_on_the_scans_own_grid():
    """The time model is the solver's own iteration on the padded grid, field grid and L1 of the
    scan (it had been one FFT times a ratio from another FFT library's table, 2.2x short of the
    full-width bench): a finer field grid and L1 > 0 cost more, a larger frame more."""
    small = estimate.iteration_seconds((112, 112), field_upsample=1, l1_zero=True)
    fine = estimate.iteration_seconds((112, 112), field_upsample=2, l1_zero=False)
    large = estimate.iteration_seconds((496, 496), field_upsample=1, l1_zero=True)
    assert 0 < small < fine and small < large
