"""Materials of the simulated world: CT numbers and X-ray attenuation.

One table, used by the CT scanner (Hounsfield units) and the fluoroscope (linear attenuation
coefficients at an effective energy of about 60 keV, in 1/mm). Values are typical textbook
figures (NIST XCOM mass attenuation times density), not fitted to any device.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Material", "MATERIALS", "material"]


@dataclass(frozen=True)
class Material:
    name: str
    hu: float            # CT number, Hounsfield units
    mu_per_mm: float     # linear attenuation at ~60 keV, 1/mm
    description: str = ""


MATERIALS: dict[str, Material] = {
    m.name: m
    for m in [
        Material("air", -1000.0, 0.0, "air (no attenuation)"),
        Material("soft_tissue", 40.0, 0.0206, "muscle-like soft tissue, 1.05 g/cm3"),
        Material("fat", -100.0, 0.0180, "adipose tissue, 0.95 g/cm3"),
        Material("marrow", -50.0, 0.0190, "yellow marrow of the medullary canal"),
        Material("cancellous_bone", 300.0, 0.0280, "trabecular bone, ~1.18 g/cm3"),
        Material("cortical_bone", 1500.0, 0.0600, "cortical bone, ~1.92 g/cm3"),
        Material("steel", 3071.0, 0.9500, "stainless steel (pins, beads, instruments), 7.9 g/cm3"),
        Material("titanium", 3071.0, 0.2800, "titanium alloy, 4.4 g/cm3"),
        Material("ultem", 150.0, 0.0250, "ULTEM (polyetherimide) rod, 1.27 g/cm3, radiolucent"),
        Material("foam", -900.0, 0.0020, "foam support under the limb"),
        Material("table", 0.0, 0.0080, "carbon-fibre OR table top"),
    ]
}


def material(name: str) -> Material:
    """Look up a material by name; ``ValueError`` lists the known names."""
    try:
        return MATERIALS[name]
    except KeyError:
        raise ValueError(
            f"unknown material {name!r}; known materials: {', '.join(sorted(MATERIALS))}"
        ) from None
