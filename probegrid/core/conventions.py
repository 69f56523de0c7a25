"""Every convention probegrid writes, as one record for manifests.

The conventions themselves are *owned* (defined, documented and tested) by the modules that use
them: face order and orientation by :mod:`probegrid.core.cubemap`, layouts by
:mod:`probegrid.core.layouts`, the SH basis by :mod:`probegrid.core.sh`, roughness and lobes by
:mod:`probegrid.core.lobes`, light units by :mod:`probegrid.core.lights`. This module only gathers them,
in words and numbers, so that every file the project writes can carry them; a test checks each
statement here against the owning module's behaviour.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from probegrid.core.cubemap import FACE_NAMES

__all__ = ["CONVENTIONS_VERSION", "Conventions", "conventions"]

CONVENTIONS_VERSION = 2


@dataclass(frozen=True)
class Conventions:
    """The conventions record written into every manifest (JSON-serialisable)."""

    version: int = CONVENTIONS_VERSION
    world_frame: str = "glTF: right-handed, +Y up, -Z forward; units metres unless the scene says"
    cube_face_order: list[str] = field(default_factory=lambda: list(FACE_NAMES))
    cube_face_storage: str = "each face row 0 = top; u to the right, v downward, in [-1, 1]"
    cube_texel_centres: str = "u = 2 (col + 0.5) / n - 1, v = 2 (row + 0.5) / n - 1"
    cube_texel_to_direction: dict[str, str] = field(default_factory=lambda: {
        "+X": "( 1, -v, -u)",
        "-X": "(-1, -v,  u)",
        "+Y": "( u,  1,  v)",
        "-Y": "( u, -1, -v)",
        "+Z": "( u, -v,  1)",
        "-Z": "(-u, -v, -1)",
    })
    cube_gpu_lookup: str = (
        "OpenGL/Vulkan/KTX2 table: texture(cube, world_dir) returns the value stored for world_dir"
    )
    color_space: str = "linear scene-referred RGB, Rec.709/sRGB primaries, D65"
    radiance_units: str = (
        "radiance in the input image's units (relative) for filtered environments; photometric "
        "for baked scenes: radiance in cd/m^2 (nits), irradiance in lux, so a 1 cd point light "
        "at 1 m gives irradiance 1"
    )
    texel_dtype: str = "float32 in memory; float16 (half) or float32 EXR on disk"
    incoming_map: str = "radiance arriving at the point from each direction (IncomingLight)"
    diffuse_map: str = (
        "irradiance / pi: the outgoing radiance of a white Lambertian surface with normal N; "
        "a constant environment of radiance L gives L everywhere"
    )
    specular_map: str = (
        "GGX split-sum prefiltered radiance (n = v = r): sum L(w) D(h) max(0, R.w) / sum "
        "D(h) max(0, R.w) over solid angle; constant L gives L at every level"
    )
    roughness_to_mip: str = (
        "perceptual roughness r = level / (levels - 1) (glTF roughnessFactor), alpha = r^2; "
        "level 0 is the unblurred image"
    )
    sh_basis: str = (
        "real spherical harmonics, bands 0-2, 9 coefficients, index l(l+1)+m, no Condon-Shortley "
        "phase, Ramamoorthi & Hanrahan 2001 constants"
    )
    sh_constants: dict[str, str] = field(default_factory=lambda: {
        "Y00": "0.282095",
        "Y1-1": "0.488603 y",
        "Y10": "0.488603 z",
        "Y11": "0.488603 x",
        "Y2-2": "1.092548 xy",
        "Y2-1": "1.092548 yz",
        "Y20": "0.315392 (3z^2 - 1)",
        "Y21": "1.092548 xz",
        "Y22": "0.546274 (x^2 - y^2)",
    })
    sh_coefficients: str = (
        "radiance coefficients L_lm = integral L(w) Y_lm(w) dw (RGB); irradiance "
        "E(n) = sum A_l L_lm Y_lm(n) with A0 = pi, A1 = 2pi/3, A2 = pi/4"
    )
    dfg_lut: str = (
        "split-sum DFG for GGX: x = N.V, y = perceptual roughness; channels (A, B) with "
        "specular = prefiltered * (F0 A + B)"
    )
    equirect_layout: str = "centre column = +X, u increasing toward +Z, top row = +Y"
    angular_layout: str = (
        "Debevec angular map: u = Dx r, v = Dy r, r = acos(Dz) / (pi sqrt(Dx^2 + Dy^2)), "
        "image up = +v, centre = +Z"
    )
    hcross_layout: str = "4x3: row 1 = -X +Z +X -Z, +Y above +Z, -Y below +Z, faces upright"
    vcross_layout: str = "3x4: +Y; -X +Z +X; -Y; -Z at the bottom rotated 180 degrees"
    surfaces: str = (
        "glTF materials as Lambertian: albedo baseColorFactor * baseColorTexture * COLOR_0; the "
        "front is the winding's side, normalize((b - a) x (c - a)); a doubleSided back face "
        "reflects with the flipped normal, a single-sided back face is black; emission "
        "(emissiveFactor * emissiveStrength * emissiveTexture, cd/m^2) leaves the front only, "
        "whatever doubleSided; a ray stops at a hit with probability p = coverage * (1 - T), "
        "T = transmissionFactor * transmissionTexture.r, coverage 1 (OPAQUE), alpha >= "
        "alphaCutoff (MASK: holes pass every ray) or alpha (BLEND), alpha = baseColorFactor.a "
        "* baseColorTexture.a * COLOR_0.a; thin-walled transmission: a ray that passes carries "
        "((1 - coverage) + coverage T baseColor.rgb) / (1 - p) per channel (the light through "
        "glass tinted by its base colour, through holes untinted), no refraction, no specular "
        "lobe; a probe's view of a punctual light takes the product of the expected share "
        "(1 - coverage) + coverage T baseColor.rgb on its way; an emitter emits where, and as "
        "much as, p (its light sampling and a probe's exact view of it alike)"
    )
    light_units: str = (
        "KHR_lights_punctual: point and spot intensity in candela, directional in lux; "
        "falloff max(min(1 - (d/range)^4, 1), 0) / d^2 (the specification's recommended "
        "window; 1/d^2 without range)"
    )


def conventions() -> dict[str, Any]:
    """The conventions record as a JSON-ready dict."""
    return asdict(Conventions())
