"""Stores that cannot lie (issue #29): every fault of the issue reproduced on a small scan.

In each, the final store is identical to an uninterrupted run, or the run is refused in one
line with nothing written.
"""

import shutil
import sys
import warnings

import cloudpickle
import numpy as np
import pytest
import zarr

from pwf_dask import cli
from pwf_dask.simulation import simulate_scan
from pwf_dask.stores import integrity, scan_io

RUN = ["--max-iter", "15"]
COMPARED = ("phase", "attenuation", "iterations", "delta", "beta", "fsc_delta")


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A 32 x 48, 6-angle, K = 2 scan and its uninterrupted reconstruction."""
    d = tmp_path_factory.mktemp("integrity")
    scan, recon = d / "scan.zarr", d / "recon.zarr"
    simulate_scan(scan, preset="demo", shape=(32, 48), angles=6, positions=2, seed=1, progress=False)
    assert cli.main(["run", str(scan), str(recon), *RUN, "--figures", str(d / "figs")]) == 0
    return scan, recon


def _copy(finished, tmp_path):
    scan, recon = finished
    shutil.copytree(recon, tmp_path / "recon.zarr")
    return scan, tmp_path / "recon.zarr"


def assert_same_store(a, b):
    ga, gb = zarr.open_group(str(a), mode="r"), zarr.open_group(str(b), mode="r")
    for name in COMPARED:
        np.testing.assert_array_equal(ga[name][...], gb[name][...], err_msg=name)


def _rerun(scan, recon, tmp_path, capsys):
    capsys.readouterr()
    assert cli.main(["run", str(scan), str(recon), *RUN, "--figures", str(tmp_path / "figs")]) == 0
    return capsys.readouterr().err


def _flip(path, n=16):
    data = bytearray(path.read_bytes())
    for k in range(n):
        data[len(data) // 3 + k] ^= 0xFF
    path.write_bytes(bytes(data))


def test_chunks_carry_checksums(finished):
    g = zarr.open_group(str(finished[1]), mode="r")
    assert all(integrity.has_checksums(arr) for _, arr in g.arrays())


@pytest.mark.parametrize(
    "damage",
    ["deleted", "flipped", "truncated", "garbage"],
)
def test_damaged_phase_chunk_is_named_and_recomputed(finished, tmp_path, capsys, damage):
    """Issue #29: a deleted chunk read as NaN (FSC 31 µm), a flipped one as 3.4e38; now each
    is named by `verify` and by `run`, which recomputes its projection to the same values."""
    scan, recon = _copy(finished, tmp_path)
    chunk = integrity.chunk_path(recon, "phase", (0, 5, 0, 0))
    if damage == "deleted":
        chunk.unlink()
    elif damage == "flipped":
        _flip(chunk)
    elif damage == "truncated":
        chunk.write_bytes(chunk.read_bytes()[:10])
    else:
        chunk.write_bytes(b"not a zstd frame at all")
    capsys.readouterr()
    assert cli.main(["verify", str(recon)]) == 1
    out = capsys.readouterr().out
    assert "phase chunk (0, 5, 0, 0)" in out
    err = _rerun(scan, recon, tmp_path, capsys)
    assert "phase chunk (0, 5, 0, 0)" in err and "recomputed" in err
    assert "Traceback" not in err
    assert_same_store(recon, finished[1])
    assert cli.main(["verify", str(recon)]) == 0


def test_missing_delta_chunk_is_recomputed_by_tomo(finished, tmp_path, capsys):
    """Issue #29: `tomo` reported 0 blocks to compute and left NaN."""
    _, recon = _copy(finished, tmp_path)
    integrity.chunk_path(recon, "delta", (1, 0, 0, 0)).unlink()
    capsys.readouterr()
    assert cli.main(["tomo", str(recon)]) == 0
    assert "row block (1, 0) is missing" in capsys.readouterr().err
    assert_same_store(recon, finished[1])


def test_damaged_bookkeeping_chunk_recomputes_its_projection(finished, tmp_path, capsys):
    scan, recon = _copy(finished, tmp_path)
    integrity.chunk_path(recon, "iterations", (1, 2)).write_bytes(b"\x28\xb5")
    err = _rerun(scan, recon, tmp_path, capsys)
    assert "iterations chunk (1, 2)" in err
    assert_same_store(recon, finished[1])


def test_tomo_alone_refuses_damaged_projections_in_one_line_and_run_recomputes(finished, tmp_path, capsys):
    """Retrieval finished, tomography not begun: a flipped chunk is found by the tomography
    task that reads it; `tomo` names it in one line, `run` recomputes it and goes on."""
    scan, recon = _copy(finished, tmp_path)
    g = zarr.open_group(str(recon), mode="r+")
    for name in ("delta", "beta", "tomo_done"):
        del g[name]
    _flip(integrity.chunk_path(recon, "attenuation", (1, 4, 0, 0)))
    capsys.readouterr()
    assert cli.main(["tomo", str(recon), "--center-um", str(g.attrs["rotation_center_m"] * 1e6)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 or all("tomo:" in line for line in err[:-1])
    assert "attenuation chunk (1, 4, 0, 0)" in err[-1] and "Traceback" not in "\n".join(err)
    _rerun(scan, recon, tmp_path, capsys)
    assert_same_store(recon, finished[1])


def test_verify_repair_marks_damage_not_done(finished, tmp_path, capsys):
    scan, recon = _copy(finished, tmp_path)
    _flip(integrity.chunk_path(recon, "beta", (1, 0, 0, 0)))
    assert cli.main(["verify", str(recon), "--repair"]) == 1
    assert "row block (1, 0) marked not done" in capsys.readouterr().out
    assert int(zarr.open_group(str(recon))["tomo_done"][1, 0]) == 0
    _rerun(scan, recon, tmp_path, capsys)
    assert_same_store(recon, finished[1])


def test_verify_reads_a_scan_store(finished, tmp_path, capsys):
    scan = tmp_path / "scan.zarr"
    shutil.copytree(finished[0], scan)
    assert cli.main(["verify", str(scan)]) == 0
    integrity.chunk_path(scan, "projections", (1, 2, 0, 0)).unlink()
    assert cli.main(["verify", str(scan)]) == 1
    assert "projections chunk (1, 2, 0, 0): missing" in capsys.readouterr().out


@pytest.mark.parametrize("kill_at", [1, 6, 12, "attributes"])
def test_a_kill_during_creation_leaves_no_store_and_the_rerun_is_whole(
    finished, tmp_path, capsys, monkeypatch, kill_at
):
    """Issue #29: a creation killed before its attributes left a store that accepted any
    parameters. The store is built under a hidden name and renamed when whole."""
    from pwf_dask.pipeline import workflow

    scan, _ = finished
    recon = tmp_path / "recon.zarr"
    create, build, calls = scan_io.create_variable, scan_io._build_reconstruction, [0]

    def killed_create(*args, **kwargs):
        calls[0] += 1
        if calls[0] == kill_at:
            raise KeyboardInterrupt
        return create(*args, **kwargs)

    def killed_after_build(path, info, params):
        build(path, info, params)
        raise KeyboardInterrupt  # every array and attribute written, the rename not done

    if kill_at == "attributes":
        monkeypatch.setattr(scan_io, "_build_reconstruction", killed_after_build)
    else:
        monkeypatch.setattr(scan_io, "create_variable", killed_create)
    with pytest.raises(KeyboardInterrupt):
        workflow.run_scan(scan, recon, max_iter=15)
    assert not recon.exists()
    monkeypatch.undo()
    integrity.partial_path(recon).mkdir(exist_ok=True)  # what a kill -9 leaves: cleared, not trusted
    (integrity.partial_path(recon) / "zarr.json").write_text("{")
    _rerun(scan, recon, tmp_path, capsys)
    assert not integrity.partial_path(recon).exists()
    assert_same_store(recon, finished[1])


def test_resuming_with_another_scan_is_refused(finished, tmp_path, capsys):
    """Issue #29: two scans of one shape, both with coherence lengths: a resume mixed 11
    projections of one with 31 of the other. The fingerprint refuses it in one line."""
    scan, recon = _copy(finished, tmp_path)
    other = tmp_path / "other.zarr"
    simulate_scan(other, preset="demo", shape=(32, 48), angles=6, positions=2, seed=2, progress=False)
    zarr.open_group(str(recon), mode="r+")["iterations"][0, 3] = -1
    capsys.readouterr()
    assert cli.main(["run", str(other), str(recon), *RUN]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another scan" in err[0] and "reference" in err[0], err
    assert int(zarr.open_group(str(recon))["iterations"][0, 3]) == -1


def _scan_with(tmp_path, finished, edit):
    path = tmp_path / "bad.zarr"
    shutil.copytree(finished[0], path)
    g = zarr.open_group(str(path), mode="r+")
    edit(g)
    scan_io.consolidate(path)
    return path


def _set_attr(name, value):
    return lambda g: g.attrs.update({name: value})


def _complex(g):
    data = g["projections"][...]
    scan_io.create_variable(
        g,
        "projections",
        data.shape,
        (1, 1, *data.shape[2:]),
        g["projections"].metadata.dimension_names,
        "complex64",
        0,
        data.astype(np.complex64),
    )


def _angles_equal(g):
    g["angle"][...] = 3.0


@pytest.mark.parametrize(
    "edit, words",
    [
        (_set_attr("flat_dark_corrected", "false"), "flat_dark_corrected"),
        (_set_attr("energy_eV", "20000"), "energy_eV"),
        (_set_attr("energy_eV", True), "energy_eV"),
        (_set_attr("energy_eV", 1.0), "energy_eV"),
        (_set_attr("energy_eV", 50.0), "energy_eV"),
        (_complex, "complex"),
        (_angles_equal, "angles"),
    ],
    ids=["bool-as-text", "number-as-text", "number-as-bool", "energy-1", "energy-50", "complex", "angles-equal"],
)
def test_bad_scans_are_refused_in_one_line_with_nothing_written(finished, tmp_path, capsys, edit, words):
    scan = _scan_with(tmp_path, finished, edit)
    recon = tmp_path / "recon.zarr"
    capsys.readouterr()
    assert cli.main(["run", str(scan), str(recon), *RUN]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not recon.exists() and not integrity.partial_path(recon).exists()


def test_zero_positions_are_refused(tmp_path, capsys):
    scan = tmp_path / "empty.zarr"
    scan_io.create_scan(
        scan,
        n_positions=0,
        angles_deg=[0.0, 1.0],
        shape=(32, 32),
        pixel_size_m=1e-6,
        dtype="float32",
        attrs={
            "energy_eV": 2e4,
            "pixel_size_m": 1e-6,
            "sample_diffuser_distance_m": 0.1,
            "diffuser_detector_distance_m": 0.5,
            "flat_dark_corrected": True,
        },
    )
    scan_io.consolidate(scan)
    assert cli.main(["retrieve", str(scan), str(tmp_path / "r.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "position" in err[0], err


@pytest.mark.parametrize(
    "option, words",
    [
        (["--tol", "nan"], "tol"),
        (["--scheduler", "foo"], "unknown scheduler"),
        (["--scheduler", "tls://127.0.0.1:1"], "--security"),
        (["--scheduler", "tls://127.0.0.1:1", "--security", "nowhere.yaml"], "no such file"),
    ],
)
def test_bad_run_options_are_refused_before_anything_is_written(finished, tmp_path, capsys, option, words):
    recon = tmp_path / "recon.zarr"
    capsys.readouterr()
    assert cli.main(["run", str(finished[0]), str(recon), *RUN, *option]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not recon.exists()


def test_local_dashboard_listens_on_this_host_only():
    """Issue #29: ``dashboard_address=":0"`` answered from other addresses."""
    from pwf_dask.pipeline.cluster import Runner

    with Runner("local", workers=1) as runner:
        link = runner.client.dashboard_link
        assert "127.0.0.1" in link
        server = runner.client.cluster.scheduler.http_server
        hosts = {s.getsockname()[0] for s in server._sockets.values()}
        assert hosts == {"127.0.0.1"}, hosts


cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import tests/


def _die_once(marker):
    import os
    from pathlib import Path

    if not Path(marker).exists():
        Path(marker).write_text("died")
        os._exit(1)
    return os.getpid()


def test_processes_scheduler_survives_a_lost_worker(tmp_path):
    """Issue #29: `processes` aborted the run when one worker died; it is now a LocalCluster
    under nannies, as `local`: the worker is restarted and its task retried."""
    from pwf_dask.pipeline.cluster import Runner

    with Runner("processes", workers=1) as runner:
        assert runner.client is not None
        pids = runner.map(_die_once, [str(tmp_path / "marker")])
    assert (tmp_path / "marker").exists() and len(pids) == 1


def _fft_threads(default):
    from pwf_dask.pipeline.cluster import worker_fft_threads

    return worker_fft_threads(default)


def test_local_worker_processes_share_the_cores_among_their_fft_threads():
    """Two single-threaded ``processes`` workers on this machine run cores / 2 FFT threads
    each, not cores each (MKL's OpenMP oversubscribed made a scan's projections 2.3x slower)."""
    from pwf_dask.pipeline.cluster import Runner, cpu_count

    with Runner("processes", workers=2) as runner:
        threads = runner.map(_fft_threads, [runner.fft_workers()] * 2)
    assert threads == [max(1, cpu_count() // 2)] * 2


def test_workers_of_a_given_cluster_take_their_fft_threads_from_their_environment(monkeypatch):
    """Several worker processes on one host of a ``tcp://`` cluster cannot see each other:
    ``PWF_DASK_FFT_WORKERS`` in their environment sets their FFT threads."""
    from distributed import LocalCluster

    from pwf_dask.pipeline.cluster import Runner

    monkeypatch.setenv("PWF_DASK_FFT_WORKERS", "3")  # the workers' processes inherit it
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with Runner(cluster.scheduler_address) as runner:
            assert runner.fft_workers() is None  # each worker decides
            assert runner.map(_fft_threads, [None]) == [3]


def test_an_existing_cluster_survives_a_lost_worker(tmp_path):
    """Issue #29: on a cluster given by its tcp:// address, a worker that dies mid-task is
    restarted by its nanny and the task retried; the run sees every result."""
    from distributed import LocalCluster

    from pwf_dask.pipeline.cluster import Runner

    marker = str(tmp_path / "marker")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("tcp://")
        with Runner(cluster.scheduler_address) as runner:
            pids = runner.map(_die_once, [marker, marker, marker])
    assert (tmp_path / "marker").exists() and len(pids) == 3


def test_store_paths_are_absolute_before_tasks_are_sent(finished, tmp_path, monkeypatch):
    """Issue #29: relative paths were opened in the workers' working directory."""
    from pwf_dask.pipeline import workflow

    scan, recon = _copy(finished, tmp_path)
    monkeypatch.chdir(tmp_path)
    seen = []
    original = workflow._decode_task

    def spy(items, *, recon_path):
        seen.append(recon_path)
        return original(items, recon_path=recon_path)

    monkeypatch.setattr(workflow, "_decode_task", spy)
    workflow.retrieve_scan(scan, "recon.zarr", max_iter=15)
    assert seen and all(p == str(recon.resolve()) for p in seen)


@pytest.mark.parametrize("damage", ["deleted", "flipped"])
def test_a_damaged_scan_chunk_is_named_before_anything_is_computed(finished, tmp_path, capsys, damage):
    """A scan chunk that is lost (it would read as zeros) or damaged is named in one line."""
    scan = tmp_path / "scan.zarr"
    shutil.copytree(finished[0], scan)
    chunk = integrity.chunk_path(scan, "projections", (0, 4, 0, 0))
    chunk.unlink() if damage == "deleted" else _flip(chunk)
    capsys.readouterr()
    assert cli.main(["run", str(scan), str(tmp_path / "recon.zarr"), *RUN]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "projections chunk (0, 4, 0, 0)" in err[0], err
    assert not (tmp_path / "recon.zarr").exists()


def _foreign(src, dst, edit=None, **to_zarr):
    """``src`` rewritten by xarray as another tool would: its own codecs (no checksums), and
    zarr's defaults otherwise (a chunk equal to the fill value is not stored)."""
    import xarray as xr

    ds = xr.open_zarr(src).load().chunk({"position": 1, "angle": 1})
    for v in ds.variables.values():
        v.encoding = {}
    if edit is not None:
        edit(ds)
    with zarr.config.set({"array.write_empty_chunks": False}), warnings.catch_warnings():
        warnings.simplefilter("ignore", zarr.errors.ZarrUserWarning)  # consolidated metadata in v3
        ds.to_zarr(dst, mode="w", **to_zarr)
    return dst


def _sharded_dot_keys(ds):
    for v in ds.data_vars.values():
        v.encoding = {"chunk_key_encoding": {"name": "default", "configuration": {"separator": "."}}}
    ds["projections"].encoding["chunks"] = (1, 1, 16, 48)  # two chunks in each frame's shard
    ds["projections"].encoding["shards"] = (1, 1, 32, 48)


@pytest.mark.parametrize(
    "edit,to_zarr",
    [(None, {"zarr_format": 2, "consolidated": False}), (_sharded_dot_keys, {})],
    ids=["zarr v2 unconsolidated", "v3 sharded with dot keys"],
)
def test_another_writers_scan_gives_the_same_reconstruction(finished, tmp_path, capsys, edit, to_zarr):
    """The contract's scan as xarray writes it in other layouts reads as pwf-dask's own: the
    chunk checks that catch a lost pwf-dask chunk do not apply to another writer's keys."""
    scan = _foreign(finished[0], tmp_path / "foreign.zarr", edit, **to_zarr)
    capsys.readouterr()
    assert cli.main(["run", str(scan), str(tmp_path / "recon.zarr"), *RUN, "--figures", str(tmp_path / "f")]) == 0
    assert "consolidated" not in capsys.readouterr().err
    assert_same_store(finished[1], tmp_path / "recon.zarr")


def test_a_zero_dark_frame_that_another_writer_left_out_reads_as_zeros(finished, tmp_path):
    from pwf_dask.pipeline import workflow

    def zero_dark(ds):
        ds["dark"] = ds["dark"] * 0

    scan = _foreign(finished[0], tmp_path / "foreign.zarr", zero_dark)
    assert not (scan / "dark" / "c" / "0" / "0").exists()
    ds, info = scan_io.open_scan(scan)
    _, flat, dark, _ = workflow._scan_frames(scan)
    np.testing.assert_array_equal(dark, 0)
    assert info.has_dark and flat.shape == dark.shape


def test_a_frame_missing_from_another_writers_scan_is_refused_in_one_line(finished, tmp_path, capsys):
    """Zarr reads a chunk another writer does not hold as its fill value: a frame of one value,
    refused by name rather than retrieved as a blank projection."""
    scan = _foreign(finished[0], tmp_path / "foreign.zarr", zarr_format=2)
    (scan / "projections" / "1.3.0.0").unlink()
    capsys.readouterr()
    assert cli.main(["run", str(scan), str(tmp_path / "recon.zarr"), *RUN]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "position 1, angle 3" in err[0] and "one value in every pixel" in err[0], err
    assert not (tmp_path / "recon.zarr").exists()


def test_verify_reads_another_writers_scan_as_intact(finished, tmp_path, capsys):
    scan = _foreign(finished[0], tmp_path / "foreign.zarr", zarr_format=2)
    capsys.readouterr()
    assert cli.main(["verify", str(scan)]) == 0
    out = capsys.readouterr().out
    assert "no checksums (written by another tool" in out and "intact" in out, out
