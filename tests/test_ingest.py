"""pwf-dask ingest: TIFF and HDF5 (DXchange) detector files into a CONTRACT §1 scan store."""

import h5py
import numpy as np
import pytest
import tifffile

from pwf_dask import cli
from pwf_dask.simulation import simulate_scan
from pwf_dask.stores import scan_io
from pwf_dask.stores.ingest import ingest_scan, read_angles_deg

GEOMETRY = dict(
    energy_eV=10_000.0, pixel_size_m=0.65e-6, sample_diffuser_distance_m=3e-3, diffuser_detector_distance_m=0.02
)
GEOMETRY_ARGS = [
    "--energy-eV",
    "10000",
    "--pixel-size-m",
    "0.65e-6",
    "--sample-diffuser-distance-m",
    "3e-3",
    "--diffuser-detector-distance-m",
    "0.02",
]


@pytest.fixture(scope="module")
def source_scan(tmp_path_factory):
    """A simulated raw-count scan (11 angles so that natural file order matters, K = 2)."""
    path = tmp_path_factory.mktemp("src") / "scan.zarr"
    simulate_scan(path, preset="demo", shape=(32, 48), angles=11, positions=2, seed=4, progress=False)
    ds, info = scan_io.open_scan(path)
    return ds.load(), info


def assert_same_scan(path, ds, info):
    got, got_info = scan_io.open_scan(path)  # validates CONTRACT §1, values included
    assert got["projections"].dtype == np.uint16
    np.testing.assert_array_equal(got["projections"].values, ds["projections"].values)
    np.testing.assert_array_equal(got["reference"].values, ds["reference"].values)
    np.testing.assert_array_equal(got["flat"].values, ds["flat"].values)
    np.testing.assert_array_equal(got["dark"].values, ds["dark"].values)
    np.testing.assert_allclose(got_info.angles_deg, info.angles_deg)
    for name in ("energy_eV", "pixel_size_m", "sample_diffuser_distance_m", "diffuser_detector_distance_m"):
        assert getattr(got_info, name) == pytest.approx(getattr(info, name))
    assert not got_info.flat_dark_corrected


def test_tiff_files_per_angle_and_stacks(source_scan, tmp_path):
    ds, info = source_scan
    proj = ds["projections"].values
    # position 0: one file per angle, named so that plain string order would be wrong
    for i in range(proj.shape[1]):
        tifffile.imwrite(tmp_path / f"p0_proj_{i}.tif", proj[0, i])
    # position 1: one multi-page stack
    tifffile.imwrite(tmp_path / "p1_stack.tif", proj[1], photometric="minisblack")
    for k in range(2):
        tifffile.imwrite(tmp_path / f"ref_{k}.tif", ds["reference"].values[k])
    tifffile.imwrite(tmp_path / "flat.tif", ds["flat"].values)
    # three identical darks: averaged, and the average is the frame itself
    tifffile.imwrite(tmp_path / "darks.tif", np.stack([ds["dark"].values] * 3), photometric="minisblack")
    out = tmp_path / "ingested.zarr"
    argv = [
        "ingest",
        str(out),
        "--projections",
        str(tmp_path / "p0_proj_*.tif"),
        str(tmp_path / "p1_stack.tif"),
        "--reference",
        str(tmp_path / "ref_0.tif"),
        str(tmp_path / "ref_1.tif"),
        "--flat",
        str(tmp_path / "flat.tif"),
        "--dark",
        str(tmp_path / "darks.tif"),
        "--angles",
        "0",
        "180",
        *GEOMETRY_ARGS,
    ]
    assert cli.main(argv) == 0
    assert_same_scan(out, ds, info)


def test_dxchange_hdf5(source_scan, tmp_path):
    ds, info = source_scan
    h5 = tmp_path / "scan.h5"
    with h5py.File(h5, "w") as f:
        f["/exchange/data"] = ds["projections"].values[0]
        f["/exchange/data_white"] = np.stack([ds["reference"].values[0]] * 2)  # averaged
        f["/exchange/data_dark"] = ds["dark"].values[None]
        f["/exchange/theta"] = np.deg2rad(info.angles_deg)
        f["/flat"] = ds["flat"].values
    out = tmp_path / "dx.zarr"
    argv = ["ingest", str(out), "--dxchange", str(h5), "--flat", f"{h5}:/flat", "--angles-unit", "rad"]
    assert cli.main([*argv, *GEOMETRY_ARGS]) == 0
    got, got_info = scan_io.open_scan(out)
    assert got_info.n_positions == 1
    np.testing.assert_allclose(got_info.angles_deg, info.angles_deg, atol=1e-9)
    np.testing.assert_array_equal(got["projections"].values[0], ds["projections"].values[0])
    np.testing.assert_array_equal(got["reference"].values[0], ds["reference"].values[0])


def test_hdf5_positions_in_one_dataset(source_scan, tmp_path):
    """(position, angle, y, x) projections with one reference frame per position."""
    ds, info = source_scan
    h5 = tmp_path / "k2.h5"
    with h5py.File(h5, "w") as f:
        f["proj"] = ds["projections"].values
        f["ref"] = ds["reference"].values
        f["flat"] = ds["flat"].values
        f["dark"] = ds["dark"].values
    out = ingest_scan(
        tmp_path / "k2.zarr",
        projections=f"{h5}:/proj",
        reference=f"{h5}:/ref",
        flat=f"{h5}:/flat",
        dark=f"{h5}:/dark",
        angles_range_deg=(0, 180),
        progress=False,
        **GEOMETRY,
    )
    assert_same_scan(out, ds, info)


def test_angles_from_a_text_file(tmp_path):
    f = tmp_path / "theta.txt"
    f.write_text("0\n0.5\n1.0\n")
    np.testing.assert_allclose(read_angles_deg(str(f), 3, None, "rad"), np.rad2deg([0, 0.5, 1.0]))
    with pytest.raises(ValueError, match="has 3 angles for 4 projections"):
        read_angles_deg(str(f), 4, None)


def _tiff_scan(tmp_path, ds, n_angles=None, low_frame=False):
    proj = ds["projections"].values[0].copy()
    if low_frame:
        proj[3, 5, 7] = 0  # below the dark (100 counts): negative after correction
    tifffile.imwrite(tmp_path / "proj.tif", proj[:n_angles], photometric="minisblack")
    tifffile.imwrite(tmp_path / "ref.tif", ds["reference"].values[0])
    tifffile.imwrite(tmp_path / "dark.tif", ds["dark"].values)
    return [
        "--projections",
        str(tmp_path / "proj.tif"),
        "--reference",
        str(tmp_path / "ref.tif"),
        "--dark",
        str(tmp_path / "dark.tif"),
    ]


@pytest.mark.parametrize(
    "case,message",
    [
        ("exists", "already exists"),
        ("no_files", "no file matches"),
        ("angle_count", "has 11 angles for 10 projections"),
        ("negative", "projection 3 of position 0"),
        ("no_angles", "either a start and stop or a file"),
        ("no_source", "give --projections and --reference"),
        ("flat_at_dark", "pixels are not above the dark (flat - dark <= 0), the first at row 0, column 0"),
        ("dead_pixel", "flat: 1 pixel is not above the dark (flat - dark <= 0), the first at row 5, column 7"),
        ("upstream_with_l1", "needs sample_diffuser_distance_m = 0"),
        ("energy_in_kev", "energy_eV = 10 is outside"),
        ("pixel_in_um", "pixel_size_m = 0.65 is outside"),
    ],
)
def test_bad_input_is_refused_in_one_line_and_writes_nothing(source_scan, tmp_path, capsys, case, message):
    ds, info = source_scan
    out = tmp_path / "out.zarr"
    src = _tiff_scan(tmp_path, ds, n_angles=10 if case == "angle_count" else None, low_frame=case == "negative")
    angles = ["--angles", "0", "180"]
    if case == "exists":
        out.mkdir()
        (out / "keep.txt").write_text("a user's file")
    elif case == "no_files":
        src[1] = str(tmp_path / "missing_*.tif")
    elif case == "angle_count":
        np.savetxt(tmp_path / "theta.txt", info.angles_deg)
        angles = ["--angles-from", str(tmp_path / "theta.txt")]
    elif case == "no_angles":
        angles = []
    elif case == "no_source":
        src = []
    elif case in ("flat_at_dark", "dead_pixel"):
        flat = ds["dark"].values.copy()
        if case == "dead_pixel":  # one pixel that does not respond to the beam
            flat = ds["flat"].values.copy()
            flat[5, 7] = ds["dark"].values[5, 7]
        tifffile.imwrite(tmp_path / "flat.tif", flat)
        src += ["--flat", str(tmp_path / "flat.tif")]
    elif case == "upstream_with_l1":  # GEOMETRY_ARGS has L1 = 3 mm
        src += ["--diffuser-upstream-m", "5e-3"]
    geometry = list(GEOMETRY_ARGS)
    if case == "energy_in_kev":  # a unit slip: keV for eV
        geometry[geometry.index("--energy-eV") + 1] = "10"
    elif case == "pixel_in_um":  # um for m
        geometry[geometry.index("--pixel-size-m") + 1] = "0.65"
    assert cli.main(["ingest", str(out), *src, *angles, *geometry]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("pwf-dask ingest: error:") and message in err, err
    if case == "exists":
        assert (out / "keep.txt").read_text() == "a user's file"
    else:
        assert not out.exists()


def test_raw_counts_without_flat_or_dark_are_ingested_with_a_one_line_warning(source_scan, tmp_path, capsys):
    """Issue #28: nothing says the counts carry the detector's dark offset unless we do."""
    ds, _ = source_scan
    src = _tiff_scan(tmp_path, ds)[:4]  # projections and reference, no dark
    out = tmp_path / "out.zarr"
    assert cli.main(["ingest", str(out), *src, "--angles", "0", "180", *GEOMETRY_ARGS]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(err) == 1 and err[0].startswith("pwf-dask: warning: no flat and no dark"), err
    assert scan_io.open_scan(out)[1].has_dark is False


def test_the_detectors_full_scale_is_recorded_and_finds_the_saturated_pixels(tmp_path):
    """8-bit frames are stored as float32, where a type maximum no longer marks saturation: the
    ingest records 255 (the sources' type maximum) or the full scale given (a 12-bit camera's
    4095 in 16-bit files), and the retrieval's saturated pixels are read against it."""
    from pwf_dask.physics.detector import saturated_pixels

    rng = np.random.default_rng(0)
    frames = (rng.random((3, 32, 48)) * 150 + 50).astype(np.uint8)
    frames[:, 5, 7] = 255
    for i, f in enumerate(frames):
        tifffile.imwrite(tmp_path / f"p{i}.tif", f)
    tifffile.imwrite(tmp_path / "ref.tif", frames[0])
    sources = dict(projections=str(tmp_path / "p*.tif"), reference=str(tmp_path / "ref.tif"), angles_range_deg=(0, 180))
    with pytest.warns(UserWarning, match="no flat and no dark"):
        ingest_scan(tmp_path / "eight.zarr", **sources, **GEOMETRY, progress=False)
    ds, info = scan_io.open_scan(tmp_path / "eight.zarr")
    assert ds["projections"].dtype == np.float32 and info.attrs[scan_io.FULL_SCALE_ATTR] == 255
    frame = ds["projections"].values[0, 1]
    assert saturated_pixels(frame) is None  # float32: its type has no full scale
    assert np.argwhere(saturated_pixels(frame, full_scale=info.attrs[scan_io.FULL_SCALE_ATTR])).tolist() == [[5, 7]]
    with pytest.warns(UserWarning):
        ingest_scan(tmp_path / "twelve.zarr", **sources, **GEOMETRY, full_scale_counts=4095, progress=False)
    assert scan_io.open_scan(tmp_path / "twelve.zarr")[1].attrs[scan_io.FULL_SCALE_ATTR] == 4095
    with pytest.raises(scan_io.ScanError, match="full_scale_counts must be a positive"):
        ingest_scan(tmp_path / "never.zarr", **sources, **GEOMETRY, full_scale_counts=0, progress=False)
    assert not (tmp_path / "never.zarr").exists()
