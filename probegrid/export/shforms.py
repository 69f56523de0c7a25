"""Nine SH coefficients in each consumer's convention, labelled, for ``sh.json``.

probegrid stores radiance coefficients ``L_lm`` (real SH, index ``l(l+1)+m``, no Condon-Shortley
phase, ``Y_lm = K_lm p_lm(x, y, z)`` with the positive constants of :mod:`probegrid.core.sh`);
irradiance is ``E(n) = sum A_l L_lm Y_lm(n)``, ``A = (pi, 2pi/3, pi/4)``. The forms:

``threejs``
    three.js ``LightProbe`` / ``SphericalHarmonics3`` and the ``LightProbeGrid`` atlas: the same
    radiance ``L_lm`` in the same basis (``shGetIrradianceAt`` multiplies by ``A_l K_lm``:
    0.886227, 2 x 0.511664, 2 x 0.429043, 0.743125 / 0.247708, 0.429043).
``filament``
    Filament's pre-scaled form (``IndirectLight::Builder::irradiance(3, sh)``, what ``cmgen``
    prints): ``f_i = A_l K_lm L_lm / pi`` so that the shader's
    ``Irradiance_SphericalHarmonics(n) = f0 + f1 y + f2 z + f3 x + f4 yx + f5 yz + f6 (3z^2 - 1)
    + f7 zx + f8 (x^2 - y^2)`` is irradiance / pi (Filament's diffuse term multiplies it by the
    diffuse colour).
``ext_lights_image_based``
    glTF ``EXT_lights_image_based.irradianceCoefficients`` as Babylon.js reads them
    (``SphericalHarmonics.FromArray``, then ``convertIrradianceToLambertianRadiance``):
    *irradiance* coefficients ``E_lm = A_l L_lm`` in Babylon's basis, whose constants for
    ``l1-1, l11, l2-1, l21`` are negative (the Condon-Shortley phase, ``SH3ylmBasisConstants`` in
    Babylon's sphericalPolynomial.ts), so those four coefficients change sign.

All three describe the same function of the world direction (glTF frame, +Y up); the tests
evaluate each consumer's polynomial and compare it with :func:`probegrid.core.sh.irradiance`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ext_lights_image_based", "filament_prescaled", "sh_forms"]

#: A_l per coefficient (clamped-cosine convolution)
_A = np.array([np.pi] + [2 * np.pi / 3] * 3 + [np.pi / 4] * 5)
#: K_lm of probegrid's basis with polynomials 1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2
_K = np.array([0.5 * np.sqrt(1 / np.pi)] + [np.sqrt(3 / (4 * np.pi))] * 3
              + [0.5 * np.sqrt(15 / np.pi)] * 2 + [0.25 * np.sqrt(5 / np.pi)]
              + [0.5 * np.sqrt(15 / np.pi)] + [0.25 * np.sqrt(15 / np.pi)])
#: Babylon's basis signs relative to probegrid's (Condon-Shortley on m = +-1)
_BABYLON_SIGN = np.array([1, -1, 1, -1, 1, -1, 1, -1, 1], dtype=np.float64)


def _check(L: ArrayLike) -> NDArray[np.float64]:
    c = np.asarray(L, dtype=np.float64)
    if c.shape[-2:] != (9, 3):
        raise ValueError(f"SH coefficients must be (..., 9, 3), got shape {c.shape}")
    return c


def filament_prescaled(L: ArrayLike) -> NDArray[np.float64]:
    """Filament's pre-scaled irradiance / pi coefficients (see the module docstring)."""
    return _check(L) * (_A * _K / np.pi)[:, None]


def ext_lights_image_based(L: ArrayLike) -> NDArray[np.float64]:
    """``EXT_lights_image_based`` irradiance coefficients in Babylon's signs."""
    return _check(L) * (_A * _BABYLON_SIGN)[:, None]


def sh_forms(L: ArrayLike) -> dict[str, Any]:
    """The radiance SH ``L`` (``(9, 3)``) in every consumer's form, each with its meaning."""
    c = _check(L)
    return {
        "threejs": {"coefficients": c.tolist(),
                    "meaning": "radiance L_lm, three.js LightProbe.sh / LightProbeGrid "
                               "(same basis as probegrid)"},
        "filament": {"coefficients": filament_prescaled(c).tolist(),
                     "meaning": "Filament pre-scaled: irradiance/pi = f0 + f1 y + f2 z + f3 x + "
                                "f4 yx + f5 yz + f6 (3z^2-1) + f7 zx + f8 (x^2-y^2) "
                                "(IndirectLight::Builder::irradiance(3, sh))"},
        "ext_lights_image_based": {
            "coefficients": ext_lights_image_based(c).tolist(),
            "meaning": "irradiance E_lm = A_l L_lm in Babylon's basis (negative constants on "
                       "l1-1, l11, l2-1, l21): EXT_lights_image_based.irradianceCoefficients"},
    }
