"""Gridding FBP (issue #31) against the direct backprojector and scikit-image's iradon."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from skimage.data import shepp_logan_phantom
from skimage.transform import iradon, radon, resize

from pwf_dask.tomo import gridrec, tomography

pytestmark = pytest.mark.skipif(not gridrec.available(), reason="finufft is not installed")


def _smooth_phantom(n: int, sigma_px: float = 2.0) -> np.ndarray:
    """Shepp-Logan blurred to the band a reconstruction holds: the two FBPs interpolate the
    filtered projections differently (linear against band-limited), which shows at edges only."""
    img = resize(shepp_logan_phantom(), (n, n))
    c = np.arange(n) - (n - 1) / 2
    img[np.hypot(*np.meshgrid(c, c)) > 0.38 * n] = 0  # inside radon's circle, once blurred
    return gaussian_filter(img, sigma_px)


def _relative_rms(a, b, inside) -> float:
    return float(np.sqrt(((a - b)[..., inside] ** 2).mean() / (b[..., inside] ** 2).mean()))


@pytest.mark.parametrize("n, offset_px", [(95, 0.0), (128, 0.0), (128, 3.3), (96, -7.5)])
def test_gridrec_matches_the_backprojector_inside_the_field_of_view(n, offset_px):
    img = _smooth_phantom(n)
    theta = np.linspace(0, 180, 180, endpoint=False)
    sino = radon(img, theta=theta, circle=True).T
    rows = np.stack([sino, 0.5 * sino], axis=1)  # two rows of one block
    if offset_px:  # the axis off the frame centre: the sinogram shifted on the detector
        from scipy.ndimage import shift

        rows = shift(rows, (0, 0, offset_px), order=3, mode="constant")
    p = 0.65e-6
    ref = tomography.filtered_back_projection(rows, theta, p, center_offset_m=offset_px * p)
    ours = gridrec.gridrec_back_projection(rows, theta, p, center_offset_m=offset_px * p)
    assert ours.shape == ref.shape and ours.dtype == np.float32
    c = np.arange(n) - (n - 1) / 2
    inside = np.hypot(*np.meshgrid(c, c)) < 0.45 * n - abs(offset_px) - 2
    assert _relative_rms(ours, ref, inside) < 0.01
    np.testing.assert_allclose(ours[1], 0.5 * ours[0], atol=1e-5 * np.abs(ours).max())


def test_gridrec_matches_skimage_iradon_and_any_angle_order():
    n = 95
    img = _smooth_phantom(n)
    theta = np.linspace(0, 180, 120, endpoint=False)
    sino = radon(img, theta=theta, circle=True)
    ref = iradon(sino, theta=theta, filter_name="ramp", circle=True)
    order = np.random.default_rng(0).permutation(theta.size)
    ours = gridrec.gridrec_back_projection(sino.T[order][:, None, :], theta[order], 1.0)[0]
    ours = np.flipud(ours)  # scikit-image rows run against our v axis
    yy, xx = np.mgrid[:n, :n]
    inside = (yy - n // 2) ** 2 + (xx - n // 2) ** 2 < (n // 2 - 2) ** 2
    assert _relative_rms(ours, ref, inside) < 0.01


def test_fbp_dispatch_records_the_method_and_falls_back():
    sino = np.random.default_rng(1).normal(size=(30, 2, 48)).astype(np.float32)
    theta = np.linspace(0, 180, 30, endpoint=False)
    direct = tomography.back_projection(sino, theta, 1e-6, method="backproject")
    np.testing.assert_array_equal(direct, tomography.filtered_back_projection(sino, theta, 1e-6))
    assert tomography.resolve_fbp("auto", np) == "gridrec"
    with pytest.raises(ValueError, match="fbp"):
        tomography.resolve_fbp("fourier", np)


def test_tomo_records_the_fbp_and_never_mixes_two(tmp_path):
    """`--fbp` is recorded; `tomo` with the other method makes every row block again."""
    import xarray as xr

    from pwf_dask import cli

    scan, recon = tmp_path / "s.zarr", tmp_path / "r.zarr"
    assert cli.main(["simulate", str(scan), "--preset", "demo", "--shape", "32", "48", "--angles", "6"]) == 0
    assert cli.main(["run", str(scan), str(recon), "--max-iter", "10", "--fbp", "backproject"]) == 0
    before = xr.open_zarr(recon)
    assert before.attrs["fbp"] == "backproject"
    delta_bp = before["delta"].values
    center = before.attrs["rotation_center_m"] * 1e6
    assert cli.main(["tomo", str(recon), "--fbp", "gridrec", "--center-um", repr(center)]) == 0
    after = xr.open_zarr(recon)
    assert after.attrs["fbp"] == "gridrec" and (after["tomo_done"].values == 1).all()
    delta_gr = after["delta"].values
    assert not np.array_equal(delta_gr, delta_bp)
    scale = np.abs(delta_bp).max()
    assert np.sqrt(np.mean((delta_gr - delta_bp) ** 2)) < 0.05 * scale  # the same tomogram, not a mix


def test_a_bad_fbp_is_refused_before_anything_is_written(tmp_path, capsys):
    from pwf_dask import cli

    scan = tmp_path / "s.zarr"
    assert cli.main(["simulate", str(scan), "--preset", "demo", "--shape", "32", "32", "--angles", "2"]) == 0
    from pwf_dask.pipeline.workflow import run_scan

    with pytest.raises(ValueError, match="fbp must be one of"):
        run_scan(scan, tmp_path / "r.zarr", fbp="fourier")
    assert not (tmp_path / "r.zarr").exists()


def test_the_device_nufft_kernel_follows_finufft_rule():
    """The ES kernel's width and shape for a requested precision: finufft's rule (w = 5 and
    beta = 2.3 w at 1e-4 on the twice-finer grid); its transform is the kernel's integral at 0."""
    from pwf_dask.tomo import nufft

    width, beta = nufft.kernel_parameters(1e-4, 2.0)
    assert width == 5 and beta == pytest.approx(2.29 * width, rel=0.01)
    assert nufft.kernel_parameters(1e-6, 1.25)[0] > nufft.kernel_parameters(1e-6, 2.0)[0]
    z = np.linspace(-width / 2, width / 2, 200001)
    integral = np.sum(nufft.es_kernel(z, width, beta)) * (z[1] - z[0])
    assert nufft.kernel_transform(8, 16, width, beta)[4] == pytest.approx(integral, rel=1e-6)
    with pytest.raises(ValueError, match="NUFFT"):
        nufft.kernel_parameters(0.0, 2.0)


@pytest.mark.gpu
@pytest.mark.parametrize("shape", [(64, 64), (95, 80)])
def test_the_device_nufft_gives_finufft(cupy, shape):
    """Issue #31: the device's own type-1 NUFFT (spreading kernel, FFT, deconvolution) gives
    finufft's sums to its requested 1e-4 (finufft's own single precision reads 0.8-1e-4 here),
    points on the period's edges included, for each transform of a batch; its real part alone
    (gridding FBP's) as the complex sums' real part."""
    if not hasattr(cupy, "ElementwiseKernel"):
        pytest.skip("no C++ compiler for the emulator's kernels")
    import finufft

    from pwf_dask.tomo import nufft

    rng = np.random.default_rng(0)
    x, y = rng.uniform(-np.pi, np.pi, (2, 4000))
    x[:10], y[10:20] = np.pi, -np.pi
    c = (rng.normal(size=(2, x.size)) + 1j * rng.normal(size=(2, x.size))).astype(np.complex64)
    exact = finufft.nufft2d1(x, y, c.astype(np.complex128), shape, eps=1e-12, isign=1)
    ours = nufft.nufft2d1(x, y, cupy.asarray(c), shape, cupy, eps=1e-4)
    assert isinstance(ours, cupy.ndarray) and ours.dtype == np.complex64 and ours.shape == (2, *shape)
    error = np.linalg.norm(cupy.asnumpy(ours) - exact) / np.linalg.norm(exact)
    assert error < 2e-4, error
    assert np.linalg.norm(cupy.asnumpy(ours[1]) - exact[1]) / np.linalg.norm(exact[1]) < 2e-4
    real = nufft.nufft2d1(x, y, cupy.asarray(c), shape, cupy, eps=1e-4, real=True)
    assert real.dtype == np.float32
    np.testing.assert_array_equal(cupy.asnumpy(real), cupy.asnumpy(ours).real)


@pytest.mark.gpu
@pytest.mark.parametrize("n", [95, 96])
def test_gridrec_on_the_device_gives_the_host_and_the_backprojector(cupy, n):
    """``--device gpu`` grids too (the default FBP there since session 73, no cufinufft): on an
    off-centre axis and uneven angles it gives the host's finufft gridrec to 2e-4 of the slice's
    maximum and the backprojector within the issue's 1 % inside the field of view."""
    if not hasattr(cupy, "ElementwiseKernel"):
        pytest.skip("no C++ compiler for the emulator's kernels")
    offset_px, p = 3.3, 0.65e-6
    theta = np.sort(np.random.default_rng(2).uniform(0, 180, 150))
    sino = radon(_smooth_phantom(n), theta=theta, circle=True).T
    from scipy.ndimage import shift

    rows = shift(np.stack([sino, 0.5 * sino], axis=1), (0, 0, offset_px), order=3, mode="constant")
    rows = rows.astype(np.float32)
    host = gridrec.gridrec_back_projection(rows, theta, p, center_offset_m=offset_px * p)
    assert tomography.resolve_fbp("auto", cupy) == "gridrec"
    device = tomography.back_projection(cupy.asarray(rows), theta, p, center_offset_m=offset_px * p)
    assert isinstance(device, cupy.ndarray) and device.dtype == np.float32
    device = cupy.asnumpy(device)
    np.testing.assert_allclose(device, host, atol=2e-4 * np.abs(host).max())
    ref = tomography.filtered_back_projection(rows, theta, p, center_offset_m=offset_px * p)
    c = np.arange(n) - (n - 1) / 2
    inside = np.hypot(*np.meshgrid(c, c)) < 0.45 * n - offset_px - 2
    assert _relative_rms(device, ref, inside) < 0.01
