"""Tomography: filtered back projection per slice, rotation centre, delta and beta (Methods).

Geometry (docs/scan-format.md §2): ``y`` is the rotation axis (detector rows); the reconstructed plane
(v, u) is centred on the axis, and a detector pixel at angle theta sees the line
x = u cos(theta) + v sin(theta), x measured from the axis. The filter is Ram-Lak, built in
the spatial domain as scikit-image's ``iradon`` does (no DC offset from sampling the ramp),
and each angle is weighted by its share of the half circle, so any angle set works.

delta = -lambda/(2 pi) FBP(phase) and beta = lambda/(2 pi) FBP(attenuation), FBP in
per-metre units: matter is positive (phase is negative for matter, docs/scan-format.md §2).
"""

from __future__ import annotations

import numpy as np

from pwf_dask import backend
from pwf_dask.backend import FFT, get_array_module
from pwf_dask.physics import background as bg


def ramlak_filter(n: int, xp=np, dtype=np.float32):
    """Ram-Lak filter on an rfft grid of length ``pad_len(n)``: the transform of the
    band-limited spatial ramp h[0] = 1/4, h[k odd] = -1/(pi k)^2 (cycles per pixel)."""
    size = pad_len(n)
    k = np.concatenate([np.arange(1, size // 2 + 1, 2), np.arange(size // 2 - 1, 0, -2)])
    h = np.zeros(size)
    h[0] = 0.25
    h[1::2] = -1 / (np.pi * k) ** 2
    return xp.asarray(np.real(np.fft.rfft(h)).astype(dtype))  # = |nu| up to band-limiting


def pad_len(n: int) -> int:
    return int(max(64, 2 ** int(np.ceil(np.log2(2 * n)))))


def angle_weights(angles_deg) -> np.ndarray:
    """d theta (rad) of each projection: half the gaps to its neighbours on the 180-degree
    circle, so that projections 180 degrees apart (0 and 180) share one direction."""
    th = np.mod(np.deg2rad(np.asarray(angles_deg, np.float64)), np.pi)
    order = np.argsort(th)
    s = th[order]
    gaps = np.diff(np.concatenate([s, [s[0] + np.pi]]))
    w_sorted = 0.5 * (gaps + np.roll(gaps, 1))
    w = np.empty_like(w_sorted)
    w[order] = w_sorted
    return w


#: output pixels per block of the CPU backprojection loop (:func:`filtered_back_projection`)
_BACKPROJECT_BLOCK = 1 << 16


def ramp_filtered(sino, fft: FFT, xp=np):
    """Ram-Lak filtered projections (angle, row, x), float32. Edge padding before the filter
    (as tomopy does): a projection that does not fall to zero at the frame edge would
    otherwise ring at radius FOV/2."""
    nx = sino.shape[-1]
    edge = nx // 2
    sino_p = xp.pad(sino, ((0, 0), (0, 0), (edge, edge)), mode="edge")
    npad = nx + 2 * edge
    size = pad_len(npad)
    if xp is np:
        import scipy.fft as sfft

        spec = sfft.rfft(sino_p, n=size, axis=-1, workers=fft.workers)
        spec *= ramlak_filter(npad)
        return sfft.irfft(spec, n=size, axis=-1, workers=fft.workers)[..., edge : edge + nx]
    spec = xp.fft.rfft(sino_p, n=size, axis=-1)
    spec *= ramlak_filter(npad, xp)
    return xp.fft.irfft(spec, n=size, axis=-1)[..., edge : edge + nx]


#: ``--fbp``: gridding (the default: finufft on the host, :mod:`pwf_dask.tomo.nufft` on CuPy) or
#: the direct backprojector (the reference)
FBP_METHODS = ("auto", "gridrec", "backproject")


def resolve_fbp(method: str, xp=np) -> str:
    """The FBP that ``method`` means for array module ``xp``: "auto" is gridrec where its
    NUFFT is there (finufft on the CPU; on the GPU always, the package's own), else the backprojector."""
    if method not in FBP_METHODS:
        raise ValueError(f"fbp must be one of {', '.join(FBP_METHODS)}, got {method!r}")
    if method != "auto":
        return method
    from pwf_dask.tomo import gridrec

    return "gridrec" if gridrec.available(xp) else "backproject"


def back_projection(sinogram, angles_deg, pixel_size_m: float, center_offset_m: float = 0.0, **kw):
    """FBP by ``method`` (:data:`FBP_METHODS`, keyword; default "auto"): slices (row, v, u)
    per metre from sinograms (angle, row, x). ``n_out`` and ``fft`` as the backprojector's."""
    method = resolve_fbp(kw.pop("method", "auto"), get_array_module(sinogram))
    if method == "gridrec":
        from pwf_dask.tomo.gridrec import gridrec_back_projection

        return gridrec_back_projection(sinogram, angles_deg, pixel_size_m, center_offset_m, **kw)
    return filtered_back_projection(sinogram, angles_deg, pixel_size_m, center_offset_m, **kw)


def sinogram_block(sinogram, fft: FFT | None):
    """(xp, fft, float32 sinogram (angle, row, x)) of a block, as both FBPs take it."""
    xp = get_array_module(sinogram)
    return xp, fft or FFT.for_module(xp), xp.asarray(sinogram, dtype=xp.float32)


def filtered_back_projection(
    sinogram,
    angles_deg,
    pixel_size_m: float,
    center_offset_m: float = 0.0,
    n_out: int | None = None,
    fft: FFT | None = None,
):
    """FBP of sinograms (angle, row, x) -> slices (row, v, u), values per metre.

    ``center_offset_m`` is the rotation axis position on the detector x coordinate (0: the
    frame centre). Output grids: u, v centred on the axis, ``n_out`` pixels (default nx).
    On a CUDA device with ``backend.cuda_kernels`` the backprojection is one kernel
    (:data:`BACKPROJECT_KERNEL`).
    """
    xp, fft, sino = sinogram_block(sinogram, fft)
    nr, nx = sino.shape[1:]
    n_out = n_out or nx
    qz = filtered_columns(sino, angles_deg, fft, xp)
    x0 = -(nx - 1) / 2 * pixel_size_m - center_offset_m  # x of column 0, measured from the axis
    if backend.cuda_kernels and xp is not np and hasattr(xp, "ElementwiseKernel"):
        out = _backproject_kernel(qz, angles_deg, -x0 / pixel_size_m, n_out, xp)
    else:
        out = _backproject_loop(qz, angles_deg, x0, pixel_size_m, n_out, xp)
    out = out.reshape(nr, n_out, n_out)
    out /= pixel_size_m  # in place: a second volume-sized array is the peak of a tomography task
    return out


def filtered_columns(sino, angles_deg, fft: FFT, xp):
    """The weighted, Ram-Lak filtered projections q (angle, row, column + 1), float32, with
    two zero columns either side: a ray that leaves the detector reads zeros there, so the
    backprojection needs no masks."""
    na, nr, nx = sino.shape
    w = xp.asarray(angle_weights(angles_deg), dtype=xp.float32)
    qz = xp.zeros((na, nr, nx + 3), dtype=xp.float32)
    # filtered in batches of angles, straight into qz: the padded spectra of a whole sinogram
    # would hold ~48 bytes per sinogram element (issue #29), a batch holds ~16 MB
    size = pad_len(nx + 2 * (nx // 2))
    batch = max(1, 2**21 // max(1, nr * size))
    for start in range(0, na, batch):
        part = slice(start, min(na, start + batch))
        qz[part, :, 1 : nx + 1] = ramp_filtered(sino[part], fft, xp) * w[part, None, None]
    return qz


def _backproject_loop(qz, angles_deg, x0: float, pixel_size_m: float, n_out: int, xp):
    """sum_a q_a(t) over the angles for each output pixel (u, v), (row, pixel) as flat rows:
    t = (u cos(theta_a) + v sin(theta_a) - x0) / p the detector column (x0: x of column 0
    measured from the axis), q interpolated linearly, q(t) = qz[i] + (t - floor t) dq[i]. One
    pass per angle over the slice in array-module operations."""
    nx = qz.shape[2] - 3
    nr = qz.shape[1]
    dq = qz[:, :, 1:] - qz[:, :, :-1]
    coords = (np.arange(n_out) - (n_out - 1) / 2) * pixel_size_m
    u_all = xp.asarray(np.tile(coords, n_out))  # the output pixels, row after row
    v_all = xp.asarray(np.repeat(coords, n_out))
    out = xp.zeros((nr, n_out * n_out), dtype=xp.float32)
    cos_th = np.cos(np.deg2rad(np.asarray(angles_deg, np.float64)))
    sin_th = np.sin(np.deg2rad(np.asarray(angles_deg, np.float64)))
    # on the CPU the pixels go in blocks whose gathers stay in cache (1.4x at 512^2), into one
    # reused buffer; a GPU takes the whole slice at once
    block = _BACKPROJECT_BLOCK if xp is np else n_out * n_out
    gathered = xp.empty((nr, block), dtype=xp.float32) if xp is np else None
    for start in range(0, n_out * n_out, block):
        u, v = u_all[start : start + block], v_all[start : start + block]
        acc = out[:, start : start + block]
        for a in range(qz.shape[0]):
            t = (u * float(cos_th[a]) + v * float(sin_th[a]) - x0) / pixel_size_m
            t = xp.clip(t, -1.0, float(nx))  # column -1 and nx read zeros
            i0 = xp.floor(t)
            f = (t - i0).astype(xp.float32)
            idx = i0.astype(xp.intp) + 1  # qz's column of detector column i0
            if xp is np:
                g = gathered[:, : idx.size]  # mode="clip": raise would buffer out (indices are in range)
                np.take(qz[a], idx, axis=1, out=g, mode="clip")
                acc += g
                np.take(dq[a], idx, axis=1, out=g, mode="clip")
                g *= f
                acc += g
            else:
                acc += xp.take(qz[a], idx, axis=1) + f * xp.take(dq[a], idx, axis=1)
    return out


#: The backprojection of :func:`_backproject_loop` as the body of one CUDA element-wise kernel
#: (CuPy's ``ElementwiseKernel``; ``i`` the output element): a thread per output pixel and row
#: loops over the angles with its sum in a register and reads q twice an angle, from cache (a
#: 2560-px row of 801 angles is 8 MB). The array-module loop launches about thirteen kernels an
#: angle, each a pass over the whole slice: 0.27 s a 2560^2 slice of 801 angles on an H200
#: (session 61), 17-20 min of a scan's tomography a position. t in float32 pixels (2.4e-4 px
#: at 2560 px: the loop's float64 t interpolates the same to ~1e-5 of the slice's values).
#: Plain C as well: the CPU test compiles it in a loop over ``i`` and compares it with the loop.
BACKPROJECT_KERNEL = """
const long long npix = (long long)n_out * n_out;
const int r = (int)(i / npix);
const long long pix = i - r * npix;
const float centre = 0.5f * (float)(n_out - 1);
const float u = (float)(pix % n_out) - centre;
const float v = (float)(pix / n_out) - centre;
float acc = 0.0f;
for (int a = 0; a < na; ++a) {
    const float t = fminf(fmaxf(u * cos_th[a] + v * sin_th[a] + t0, -1.0f), (float)(nq - 3));
    const float i0 = floorf(t);
    const long long k = ((long long)a * nr + r) * nq + (long long)i0 + 1;
    acc += qz[k] + (t - i0) * (qz[k + 1] - qz[k]);
}
out = acc;
"""

#: CuPy module -> its compiled backprojection kernel
_BACKPROJECT_KERNELS: dict = {}


def _backproject_kernel(qz, angles_deg, t0: float, n_out: int, xp):
    """:func:`_backproject_loop` by :data:`BACKPROJECT_KERNEL` (compiled once per process and
    CuPy module); ``t0`` the detector column of the axis (pixels)."""
    if xp not in _BACKPROJECT_KERNELS:
        _BACKPROJECT_KERNELS[xp] = xp.ElementwiseKernel(
            "raw float32 qz, raw float32 cos_th, raw float32 sin_th, int32 na, int32 nr, int32 nq, "
            "int32 n_out, float32 t0",
            "float32 out",
            BACKPROJECT_KERNEL,
            name="pwf_backproject",
        )
    theta = np.deg2rad(np.asarray(angles_deg, np.float64))
    na, nr, nq = qz.shape
    out = xp.empty((nr, n_out * n_out), dtype=xp.float32)
    cos_th, sin_th = (xp.asarray(f(theta), dtype=xp.float32) for f in (np.cos, np.sin))
    # flat: a raw argument is indexed by its flat index (i and n are CuPy's own names)
    _BACKPROJECT_KERNELS[xp](xp.ascontiguousarray(qz).ravel(), cos_th, sin_th, na, nr, nq, n_out, t0, out)
    return out


def estimate_rotation_center(sinogram, angles_deg, pixel_size_m: float) -> float:
    """Rotation axis on detector x (m from the frame centre) by the centre-of-mass sinusoid.

    The centre of mass of a parallel projection of a compact, positive object moves as
    x_cm(theta) = c + a cos(theta) + b sin(theta); a least-squares fit over all angles gives c
    for any angle set (no 180-degree pair needed). ``sinogram`` (angle, row, x) must be
    positive for matter (-phase or attenuation) and the object must stay inside the frame.
    """
    s = np.asarray(sinogram, np.float64).sum(axis=1)
    s = np.clip(s, 0, None)
    nx = s.shape[1]
    x = (np.arange(nx) - (nx - 1) / 2) * pixel_size_m
    mass = s.sum(axis=1)
    ok = mass > 0
    if ok.sum() < 3:
        raise ValueError("rotation centre: projections hold no signal; give the centre explicitly")
    xcm = (s[ok] * x).sum(axis=1) / mass[ok]
    th = np.deg2rad(np.asarray(angles_deg, np.float64))[ok]
    a = np.stack([np.ones_like(th), np.cos(th), np.sin(th)], axis=1)
    coef, *_ = np.linalg.lstsq(a, xcm, rcond=None)
    return float(coef[0])


def rotation_center_from_opposite(sinogram, angles_deg, pixel_size_m: float) -> float | None:
    """Rotation axis (m from the frame centre) from a projection pair 180 degrees apart, or None.

    p_180(x) = p_0(2c - x), so p_180 mirrored about the frame centre is p_0 shifted by 2c;
    the shift comes from the cross-correlation peak (parabola through its three top samples).
    Gradients are correlated, not values, so a constant background does not matter.
    """
    ang = np.asarray(angles_deg, np.float64)
    step = np.median(np.diff(np.sort(ang))) if ang.size > 1 else 0.0
    best = None
    for i in range(ang.size):
        j = int(np.argmin(np.abs(ang - ang[i] - 180.0)))
        err = abs(ang[j] - ang[i] - 180.0)
        if err <= 0.25 * step + 1e-9 and (best is None or err < best[2]):
            best = (i, j, err)
    if best is None:
        return None
    s = np.asarray(sinogram, np.float64)
    a = np.gradient(s[best[0]].mean(axis=0))
    b = np.gradient(s[best[1]].mean(axis=0)[::-1])
    n = a.size
    xc = np.fft.irfft(np.fft.rfft(b, 2 * n) * np.conj(np.fft.rfft(a, 2 * n)), 2 * n)
    k = int(np.argmax(xc))
    y0, y1, y2 = xc[k - 1], xc[k], xc[(k + 1) % (2 * n)]
    den = y0 - 2 * y1 + y2
    frac = 0.5 * (y0 - y2) / den if den != 0 else 0.0
    shift = (k + frac) if k < n else (k + frac - 2 * n)
    # mirroring about index (n-1)/2 maps x -> -x, so the shift in pixels is 2c / p
    return float(-shift * pixel_size_m / 2)


def to_refractive_index(fbp_phase, fbp_attenuation, wavelength: float):
    """(delta, beta) from FBPs of phase and attenuation (per metre): -lambda/2pi, +lambda/2pi."""
    k = wavelength / (2 * np.pi)
    return -k * fbp_phase, k * fbp_attenuation


#: Tomogram slices of more than this many pixels across are searched for their sample-free
#: area on a copy binned to about this size (the quadratic is still fitted at full
#: resolution): the search iterates a plane fit and a dilation up to 20 times, 2.3 s of a
#: 2560^2 slice's 2.8 s, against 0.5 s for its gridding FBP (issue #31).
BACKGROUND_SEARCH_PX = 512


def background_mask(image):
    """Sample-free pixels of one tomogram slice (matter is positive in delta and beta, so the
    detector, which looks for matter below the background, is handed the slice negated); a
    slice wider than :data:`BACKGROUND_SEARCH_PX` is searched binned b x b, its edge rows and
    columns beyond whole bins left out of the fit. On the slice's device (NumPy or CuPy)."""
    xp = get_array_module(image)
    b = max(1, min(image.shape) // BACKGROUND_SEARCH_PX)
    if b == 1:
        return bg.detect_background(-image / (xp.abs(image).max() or 1.0), smooth_px=1.5, margin_px=2)
    ny, nx = (image.shape[0] // b) * b, (image.shape[1] // b) * b
    small = image[:ny, :nx].reshape(ny // b, b, nx // b, b).mean(axis=(1, 3))
    found = bg.detect_background(-small / (xp.abs(small).max() or 1.0), smooth_px=1.5, margin_px=1)
    mask = xp.zeros(image.shape, bool)
    mask[:ny, :nx] = xp.repeat(xp.repeat(found, b, axis=0), b, axis=1)
    return mask


#: What the slice's background fit (Methods, after the FBP) is applied to: "quadratic" both
#: tomograms over every sample-free pixel (the paper), "none" neither, "beta" the attenuation's
#: alone, "auto" (the default) both, but only over the sample-free pixels beyond the sample's
#: reach (:func:`far_background_mask`), and only on slices that have enough of them. The
#: phase's low-frequency error spreads a sample's rim into a halo around it (docs/validation.md:
#: +0.11-0.13 of delta out to 1.6 radii on the demo); a fit that reads the halo as background
#: takes the sample down with it (the demo's cylinder -2.5 % bare, -15.9 % fitted).
SLICE_BACKGROUNDS = {
    "auto": "quadratic surface per slice over the sample-free pixels beyond the sample's reach; "
    "none on slices without enough of them",
    "quadratic": "quadratic surface per slice",
    "none": "none",
    "beta": "quadratic surface per slice of beta; none on delta",
}
#: the mode a tomography run uses unless told otherwise
DEFAULT_SLICE_BACKGROUND = "auto"

#: "auto" fits only pixels at least this many of the sample's equivalent radii (the radius of
#: a disc of the sample's area in the slice) from the sample: the halo's reach. Measured on
#: the demo's cylinder at half size in a frame twice as wide (session 75): the halo falls from
#: +0.17 of delta at the rim to +0.02 one radius out.
SAMPLE_REACH_RADII = 1.0
#: ... and only on slices where such pixels cover this share of the field of view, so that the
#: quadratic is fitted around the sample rather than extrapolated from a strip of it.
MIN_FAR_FRACTION = 0.25


def check_slice_background(mode: str) -> str:
    """``mode`` if it is one of :data:`SLICE_BACKGROUNDS`, else a one-line ValueError."""
    if mode not in SLICE_BACKGROUNDS:
        raise ValueError(f"unknown slice_background {mode!r}: choose one of {', '.join(SLICE_BACKGROUNDS)}")
    return mode


def fits_background(volume: str, mode: str) -> bool:
    """Whether tomogram ``volume`` ("delta" or "beta") gets a slice background fit under ``mode``
    (under "auto", on the slices :func:`far_background_mask` finds room on)."""
    return check_slice_background(mode) in ("quadratic", "auto") or (mode == "beta" and volume == "beta")


def field_of_view(shape: tuple[int, int], xp=np):
    """The disc every angle sees of a slice centred on the axis (the FBP's inscribed circle)."""
    y = xp.arange(shape[0])[:, None] - (shape[0] - 1) / 2
    x = xp.arange(shape[1])[None, :] - (shape[1] - 1) / 2
    return y**2 + x**2 <= (0.5 * (min(shape) - 1)) ** 2


def far_background_mask(image):
    """Sample-free pixels of a slice's field of view at least :data:`SAMPLE_REACH_RADII` of the
    sample's equivalent radii from it (the sample is the field of view's pixels
    :func:`background_mask` does not call sample-free), or None where those are fewer than
    :data:`MIN_FAR_FRACTION` of the field of view: there every sample-free pixel is within
    the sample's halo, and a fit would read the halo as background. On the slice's device."""
    xp = get_array_module(image)
    background = background_mask(image)
    fov = field_of_view(image.shape, xp)
    sample = fov & ~background
    reach_px = SAMPLE_REACH_RADII * float(xp.sqrt(sample.sum() / np.pi))
    # the distance to the sample is searched on the binned grid background_mask searches on
    b = max(1, min(image.shape) // BACKGROUND_SEARCH_PX)
    ny, nx = (image.shape[0] // b) * b, (image.shape[1] // b) * b
    coarse = sample[:ny, :nx].reshape(ny // b, b, nx // b, b).any(axis=(1, 3))
    distance = backend.ndimage(xp).distance_transform_edt(~coarse) * b
    near = xp.ones(image.shape, bool)
    near[:ny, :nx] = xp.repeat(xp.repeat(distance < reach_px, b, axis=0), b, axis=1)
    far = background & fov & ~near
    return far if int(far.sum()) >= MIN_FAR_FRACTION * int(fov.sum()) else None


def far_background_masks(delta_slices) -> list:
    """:func:`far_background_mask` of each slice of delta: where "auto" fits both tomograms
    (the phase's sample, which the attenuation shares and sees less clearly)."""
    return [far_background_mask(s.astype(get_array_module(s).float64)) for s in delta_slices]


def corrected_slices(slices, volume: str, mode: str, far_masks=None):
    """``slices`` of tomogram ``volume`` with the background of ``mode`` (:data:`SLICE_BACKGROUNDS`)
    removed; under "auto" ``far_masks`` (:func:`far_background_masks` of the same slices of
    delta) says where, and a slice whose entry is None is returned as the FBP made it."""
    if not fits_background(volume, mode):
        return slices
    if mode != "auto":
        return remove_background(slices)
    if far_masks is None:
        raise ValueError('slice_background "auto" needs far_masks: far_background_masks of the slices of delta')
    # delta's masks are its own sample-free pixels already; beta's are narrowed to its own too
    return remove_background(slices, fit_masks=far_masks, detect=volume != "delta")


def remove_background(slices, degree: int = 2, fit_masks=None, detect: bool = True):
    """Subtract a quadratic surface fitted over the empty area of each slice (Methods), on the
    slices' device: with ``--device gpu`` a 2560^2 slice's ~0.5 s of host work stays on the GPU.
    ``fit_masks`` (one per slice) narrows each fit to the slice's sample-free pixels within
    the mask (to the mask itself with ``detect`` False); a slice whose mask is None is left
    as it is."""
    xp = get_array_module(slices)
    slices = xp.asarray(slices)
    # single-precision slices come back single (each fitted in double): a task then holds one
    # volume-sized float32 array here, not two float64 ones
    out = xp.empty(slices.shape, xp.float32 if slices.dtype == xp.float32 else xp.float64)
    for i in range(slices.shape[0]):
        s = slices[i].astype(xp.float64)
        if fit_masks is not None and fit_masks[i] is None:
            out[i] = s
            continue
        if fit_masks is None:
            mask = background_mask(s)
        else:
            mask = background_mask(s) & fit_masks[i] if detect else fit_masks[i]
        out[i] = bg.zero_background(s, mask, degree) if int(mask.sum()) >= bg.MIN_BACKGROUND_PIXELS else s
    return out
