"""Refractive-index decrements from xraydb: n = 1 - delta + i beta at a photon energy."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache


@dataclass(frozen=True)
class Material:
    """A material by chemical formula and density (g/cm^3)."""

    name: str
    formula: str
    density_g_cm3: float


MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        Material("cellulose", "C6H10O5", 1.5),
        # soda-lime glass, 72 SiO2 / 14 Na2O / 10 CaO / 4 MgO wt %, as molar formula
        Material("soda-lime glass", "Si1.198Na0.452Ca0.178Mg0.099O2.899", 2.5),
        Material("silicon carbide", "SiC", 3.21),
        Material("alumina", "Al2O3", 3.95),
        Material("water", "H2O", 1.0),
        Material("PMMA", "C5H8O2", 1.18),
    )
}


def material(name: str) -> Material:
    try:
        return MATERIALS[name]
    except KeyError:
        raise ValueError(f"unknown material {name!r}; known: {', '.join(sorted(MATERIALS))}") from None


@lru_cache(maxsize=256)
def delta_beta(name: str, energy_eV: float) -> tuple[float, float]:
    """(delta, beta) of a named material at ``energy_eV`` (xraydb's tabulated f1, f2)."""
    import xraydb

    m = material(name)
    delta, beta, _ = xraydb.xray_delta_beta(m.formula, m.density_g_cm3, float(energy_eV))
    return float(delta), float(beta)
