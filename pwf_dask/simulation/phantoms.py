"""Analytic phantoms with exact line integrals: spheres in a cylinder (the paper's beads), rods.

Chord lengths are computed in closed form, so the ground truth of every simulated projection
and of the refractive-index volume is exact (no voxelisation).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pwf_dask.physics.materials import delta_beta

#: beads' voxels a measure of the cylinder's own material leaves out, this many voxels beyond
#: their radius (:meth:`Phantom.cylinder_core`): the tomogram's edges spread a bead over ~2 px
CORE_BEAD_MARGIN_PX = 3


@dataclass(frozen=True)
class Sphere:
    """A sphere (bead) at (u, y, v) metres in the sample frame."""

    u_m: float
    y_m: float
    v_m: float
    radius_m: float
    material: str = "soda-lime glass"


@dataclass(frozen=True)
class Phantom:
    """A vertical cylinder (axis along y at (u, v)) with spheres embedded in it.

    Spheres lie inside the cylinder (their material replaces the cylinder's along their
    chord) or outside it entirely; the projected delta/beta sums are then exact.
    """

    cylinder_radius_m: float = 120e-6
    cylinder_u_m: float = 0.0
    cylinder_v_m: float = 0.0
    cylinder_material: str = "cellulose"
    spheres: tuple[Sphere, ...] = ()

    def line_integrals(self, angle_deg: float, x_m: np.ndarray, y_m: np.ndarray, energy_eV: float):
        """(integral of delta, integral of beta) along the beam, in metres, on the (y, x) grid.

        A detector pixel at angle theta sees the line x = u cos(theta) + v sin(theta) (docs/scan-format.md §2).
        """
        th = np.deg2rad(angle_deg)
        c, s = np.cos(th), np.sin(th)
        xx = x_m[None, :]
        yy = y_m[:, None]
        dc, bc = delta_beta(self.cylinder_material, energy_eV)
        xc = self.cylinder_u_m * c + self.cylinder_v_m * s
        chord = 2.0 * np.sqrt(np.clip(self.cylinder_radius_m**2 - (xx - xc) ** 2, 0, None))
        chord = np.broadcast_to(chord, (y_m.size, x_m.size))
        d_int = dc * chord
        b_int = bc * chord
        for sp in self.spheres:
            ds, bs = delta_beta(sp.material, energy_eV)
            xs = sp.u_m * c + sp.v_m * s
            ch = 2.0 * np.sqrt(np.clip(sp.radius_m**2 - (xx - xs) ** 2 - (yy - sp.y_m) ** 2, 0, None))
            inside = np.hypot(sp.u_m - self.cylinder_u_m, sp.v_m - self.cylinder_v_m) < self.cylinder_radius_m
            d_int = d_int + (ds - (dc if inside else 0.0)) * ch
            b_int = b_int + (bs - (bc if inside else 0.0)) * ch
        return d_int, b_int

    def cylinder_core(
        self,
        y_m: np.ndarray,
        v_m: np.ndarray,
        u_m: np.ndarray,
        radius_fraction: float = 0.5,
        bead_margin_m: float = 0.0,
    ) -> np.ndarray:
        """Boolean (y, v, u) mask of the cylinder's own material: within ``radius_fraction`` of
        its radius from the axis and more than ``bead_margin_m`` outside every sphere. Where a
        measure of the cylinder includes its beads (a quarter of the demo's core), glass's
        beta, ten times cellulose's at 10 keV, lifts even a median of the noisy beta (docs/validation.md)."""
        yy, vv, uu = np.meshgrid(np.asarray(y_m), np.asarray(v_m), np.asarray(u_m), indexing="ij")
        core = np.hypot(vv - self.cylinder_v_m, uu - self.cylinder_u_m) < radius_fraction * self.cylinder_radius_m
        for sp in self.spheres:
            core &= (yy - sp.y_m) ** 2 + (vv - sp.v_m) ** 2 + (uu - sp.u_m) ** 2 > (sp.radius_m + bead_margin_m) ** 2
        return core


@dataclass(frozen=True)
class Rods:
    """Parallel vertical rods of one material (axes along y at (u, v)), nothing inside them.

    The regime of issue #27's real scan: mm-wide PMMA rods across a wide strip, one of them
    cut by the frame's edge. Projections only (:meth:`line_integrals`); no volume truth.
    """

    u_m: tuple[float, ...]
    radii_m: tuple[float, ...]
    v_m: tuple[float, ...] | None = None
    material: str = "PMMA"
    spheres: tuple[Sphere, ...] = ()  # none: the simulator's phantom protocol

    def line_integrals(self, angle_deg: float, x_m: np.ndarray, y_m: np.ndarray, energy_eV: float):
        """(integral of delta, integral of beta) in metres on the (y, x) grid: exact chords."""
        th = np.deg2rad(angle_deg)
        d, b = delta_beta(self.material, energy_eV)
        vs = self.v_m or (0.0,) * len(self.u_m)
        chord = np.zeros(x_m.size)
        for u, v, r in zip(self.u_m, vs, self.radii_m, strict=True):
            xc = u * np.cos(th) + v * np.sin(th)
            chord += 2.0 * np.sqrt(np.clip(r * r - (x_m - xc) ** 2, 0, None))
        chord = np.broadcast_to(chord[None, :], (y_m.size, x_m.size))
        return d * chord, b * chord


def default_phantom(
    field_of_view_m: float,
    rng: np.random.Generator | None = None,
    n_beads: int = 6,
    height_m: float | None = None,
    cylinder_fraction: float = 0.72,
    bead_radius_range_m: tuple[float, float] | None = None,
) -> Phantom:
    """A toothpick-like cellulose cylinder with soda-lime glass beads inside it (the paper's sample).

    Sizes scale with the field of view: the cylinder spans ``cylinder_fraction`` of it, bead
    radii 5-12 % of it (at most 40 % of the frame height), beads placed without overlap inside
    the cylinder and the frame height.
    """
    rng = rng or np.random.default_rng(0)
    height_m = height_m or field_of_view_m
    big_r = 0.5 * cylinder_fraction * field_of_view_m
    lo, hi = bead_radius_range_m or (0.05 * field_of_view_m, 0.12 * field_of_view_m)
    # a frame of few rows (a slab of a wide detector) holds smaller beads: each must fit
    # its height with the 1.2 r margin the placement keeps
    hi = min(hi, 0.5 * height_m / 1.25)
    # and inside the cylinder, with the 1.05 r margin the placement keeps
    hi = min(hi, big_r / 1.1)
    lo = min(lo, hi)
    spheres: list[Sphere] = []
    radii = np.sort(rng.uniform(lo, hi, n_beads))[::-1]
    radii[0] = hi
    for r in radii:
        for _ in range(2000):
            rho = rng.uniform(0, big_r - r * 1.05)
            ang = rng.uniform(0, 2 * np.pi)
            u, v = rho * np.cos(ang), rho * np.sin(ang)
            y = rng.uniform(-0.5 * height_m + r * 1.2, 0.5 * height_m - r * 1.2)
            if all(
                np.sqrt((u - o.u_m) ** 2 + (v - o.v_m) ** 2 + (y - o.y_m) ** 2) > r + o.radius_m + 2e-6 for o in spheres
            ):
                spheres.append(Sphere(u, y, v, float(r)))
                break
    return Phantom(cylinder_radius_m=big_r, spheres=tuple(spheres))


# --- whole scans ---------------------------------------------------------------------------


def phantom_to_json(ph: Phantom) -> str:
    import json
    from dataclasses import asdict

    return json.dumps(asdict(ph))


def phantom_from_json(text: str) -> Phantom:
    import json

    d = json.loads(text)
    d["spheres"] = tuple(Sphere(**s) for s in d.get("spheres", ()))
    return Phantom(**d)


def refractive_index_volume(phantom: Phantom, y_m, v_m, u_m, energy_eV: float, supersample: int = 2):
    """True (delta, beta) on the (y, v, u) voxel grid, each voxel averaged over supersample^3 points.

    Each sub-sample point takes the material of the last bead containing it, else the cylinder's
    or none. The cylinder does not depend on y, so its sum over the sub-samples is taken on the
    (v, u) plane and broadcast; only the voxels a bead can reach (its bounding box) are summed
    point by point, in the same order, so every voxel holds the same float64 sum as summing whole
    volumes would (a 32 x 2560 x 2560 truth took 85 s and ~10 volumes of memory that way).
    """
    y_m, v_m, u_m = (np.asarray(a, np.float64) for a in (y_m, v_m, u_m))
    du = abs(u_m[1] - u_m[0])
    dy = abs(y_m[1] - y_m[0]) if y_m.size > 1 else du  # one slice: a cubic voxel
    off = (np.arange(supersample) + 0.5) / supersample - 0.5
    offsets = [(oy, ov, ou) for oy in off for ov in off for ou in off]
    materials = [delta_beta(phantom.cylinder_material, energy_eV)]
    materials += [delta_beta(sp.material, energy_eV) for sp in phantom.spheres]
    delta = np.empty((y_m.size, v_m.size, u_m.size))
    beta = np.empty_like(delta)
    whole = (slice(None), slice(None), slice(None))
    for out, k in ((delta, 0), (beta, 1)):
        out[...] = _point_sums(phantom, [m[k] for m in materials], y_m[:1], v_m, u_m, dy, du, offsets, whole, False)
    for sp in phantom.spheres:
        box = tuple(
            _reach(c, sp.radius_m, step) for c, step in ((y_m - sp.y_m, dy), (v_m - sp.v_m, du), (u_m - sp.u_m, du))
        )
        if any(b.start >= b.stop for b in box):
            continue
        for out, k in ((delta, 0), (beta, 1)):
            out[box] = _point_sums(phantom, [m[k] for m in materials], y_m, v_m, u_m, dy, du, offsets, box, True)
    n = supersample**3
    delta /= n  # in place: a whole truth volume is several GB at 2560 px
    beta /= n
    return delta, beta


def _reach(offset_m: np.ndarray, radius_m: float, step_m: float) -> slice:
    """The index range whose voxels (sub-samples within half a step) a bead of ``radius_m`` can
    reach along one axis; ``offset_m``: the axis' coordinates less the bead's centre."""
    near = np.flatnonzero(np.abs(offset_m) < radius_m + step_m)
    return slice(int(near[0]), int(near[-1]) + 1) if near.size else slice(0, 0)


def _point_sums(phantom: Phantom, values, y_m, v_m, u_m, dy, du, offsets, box, beads: bool) -> np.ndarray:
    """The sum over the sub-sample ``offsets`` (in order) of the material value at each point of
    the grid ``box`` of (y, v, u): the cylinder's ``values[0]`` inside it, a bead's (the last
    containing the point) where ``beads``; without beads y does not matter and one plane is summed."""
    ys, vs, us = y_m[box[0]], v_m[box[1]], u_m[box[2]]
    total = None
    for oy, ov, ou in offsets:
        yy = (ys + oy * dy)[:, None, None]
        vv = (vs + ov * du)[None, :, None]
        uu = (us + ou * du)[None, None, :]
        incyl = ((uu - phantom.cylinder_u_m) ** 2 + (vv - phantom.cylinder_v_m) ** 2) < phantom.cylinder_radius_m**2
        point = np.where(incyl, values[0], 0.0)
        if beads:
            point = np.broadcast_to(point, (ys.size, vs.size, us.size))
            for sp, value in zip(phantom.spheres, values[1:]):
                ins = ((uu - sp.u_m) ** 2 + (vv - sp.v_m) ** 2 + (yy - sp.y_m) ** 2) < sp.radius_m**2
                point = np.where(ins, value, point)
        total = point + 0.0 if total is None else total + point
    return total


#: the cylinder diameter of :func:`scan_phantom` over the frame width (0.8 x default_phantom's 0.72)
SCAN_CYLINDER_WIDTH_FRACTION = 0.8 * 0.72


#: radii of the paper's glass beads (Merck G8893, <= 106 um across; Methods, Samples): the
#: ``beads`` and ``paper`` presets draw their beads from this range, not from the frame's size
PAPER_BEAD_RADIUS_M = (25e-6, 53e-6)


def scan_phantom(
    shape: tuple[int, int],
    pixel_size_m: float,
    seed: int = 0,
    cylinder_width_fraction: float | None = None,
    bead_radius_range_m: tuple[float, float] | None = None,
) -> Phantom:
    """The phantom :func:`simulate_scan` draws for a frame of ``shape`` and its ``seed``: the
    cylinder spans :data:`SCAN_CYLINDER_WIDTH_FRACTION` of the width, one bead per 12 rows (>= 3).

    Bead radii are 5-12 % of the field of view unless ``bead_radius_range_m`` gives them in
    metres (e.g. :data:`PAPER_BEAD_RADIUS_M`); either way a bead fits the frame height and the
    cylinder, so a small frame holds smaller beads than asked for.

    ``cylinder_width_fraction`` widens (or narrows) the cylinder alone; the beads stay where
    the default draws them, inside the field of view. Above 1 the sample is wider than the
    field of view at every angle: an interior (local) scan.
    """
    ny, nx = shape
    phantom = default_phantom(
        0.8 * nx * pixel_size_m,
        np.random.default_rng(seed + 1000),
        height_m=ny * pixel_size_m,
        n_beads=max(3, ny // 12),
        bead_radius_range_m=bead_radius_range_m,
    )
    if cylinder_width_fraction is None:
        return phantom
    radius = 0.5 * cylinder_width_fraction * nx * pixel_size_m
    if any(np.hypot(s.u_m, s.v_m) + s.radius_m > radius for s in phantom.spheres):
        raise ValueError(
            f"cylinder_width_fraction {cylinder_width_fraction} is too small for the beads: use at least "
            f"{SCAN_CYLINDER_WIDTH_FRACTION:.3f}"
        )
    return replace(phantom, cylinder_radius_m=radius)
