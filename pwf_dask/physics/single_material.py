"""The single-material prior (not in the paper): the phase's low spatial frequencies from the
attenuation, for a sample of one known material.

For one material, phase = -k int delta dz and attenuation (-Re psi) = k int beta dz, so
phase = -(delta/beta) attenuation. PWF's attenuation is unambiguous at low frequencies, its
phase is not always: a thick object with sharp edges (a mm-wide rod at 6.5 um pixels, a phase
step of ~16 rad inside the outermost pixel) has steps that the pixel grid cannot hold, the
retrieved phase caps them near 2-3 rad/px, and each edge loses a different part of its step:
the phase between edges is off by tens of radians, with the same data residual as the truth
(docs/methods.md, Wide frames). The data cannot choose; the material can.

:func:`single_material_phase` keeps PWF's phase at high frequencies and takes the low ones
from -(delta/beta) attenuation, blended by Paganin's filter (Paganin et al., J. Microsc. 206,
33 (2002), Eq. 10),

    W(q) = 1 / (1 + ell^2 |q|^2),   ell^2 = lambda z (delta/beta) / (4 pi),

the frequency below which a single material's attenuation contrast outweighs its propagation
phase contrast, with z the sample-to-detector distance (L1 + L2). ell is derived from the
set-up and the material, not tuned. Wrong where the sample is not one material: a glass bead
in cellulose takes the cellulose's ratio (docs/validation.md).
"""

from __future__ import annotations

import math

import numpy as np

from pwf_dask.backend import get_array_module
from pwf_dask.physics.optics import frequency_grid


def paganin_length_m(wavelength_m: float, distance_m: float, delta_over_beta: float) -> float:
    """ell = sqrt(lambda z (delta/beta) / (4 pi)), the width of Paganin's filter (module docstring)."""
    for name, value in (
        ("wavelength_m", wavelength_m),
        ("distance_m", distance_m),
        ("delta_over_beta", delta_over_beta),
    ):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"single-material prior: {name} must be positive, got {value}")
    return math.sqrt(wavelength_m * distance_m * delta_over_beta / (4.0 * math.pi))


def paganin_filter(shape: tuple[int, int], pixel_size_m: float, length_m: float, xp=np, dtype=np.float64):
    """W(q) = 1 / (1 + ell^2 |q|^2) on the rfft half plane, q = 2 pi (u, v) in rad/m."""
    v, u = frequency_grid(shape, pixel_size_m, half=True)
    q2 = (2.0 * math.pi) ** 2 * (u * u + v * v)
    return xp.asarray(1.0 / (1.0 + length_m * length_m * q2), dtype=dtype)


def single_material_phase(
    phase,
    attenuation,
    delta_over_beta: float,
    *,
    pixel_size_m: float,
    wavelength_m: float,
    distance_m: float,
):
    """phase + W * (-(delta/beta) attenuation - phase): PWF's phase with its low frequencies
    from the attenuation (module docstring). NumPy or CuPy arrays of one shape.

    The difference is filtered on the frame mirrored into a 2x2 tile (a cosine transform's
    even extension): no edge of the frame meets another in the periodic FFT, so a rod cut by
    the frame's edge is not carried to the opposite edge.
    """
    xp = get_array_module(phase, attenuation)
    ell = paganin_length_m(wavelength_m, distance_m, delta_over_beta)
    ny, nx = phase.shape
    difference = -float(delta_over_beta) * attenuation - phase
    tile = xp.pad(difference, ((0, ny), (0, nx)), mode="symmetric")
    w = paganin_filter(tile.shape, pixel_size_m, ell, xp, tile.dtype)
    low = xp.fft.irfft2(xp.fft.rfft2(tile) * w, s=tile.shape)[:ny, :nx]
    return phase + low
