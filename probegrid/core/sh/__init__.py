"""Real spherical harmonics (SH): the project's basis, projection, irradiance, windows, rotation.

This package *owns* the project's SH convention; every other module imports it from here
(``from probegrid.core import sh``). One function per idea, for any band count: each takes
``bands`` (keyword, default 3: the 9-coefficient basis the bake and the store use, up to
:data:`MAX_BANDS`; the coefficient array must have ``bands^2`` rows) and computes the 3-band
case on its own fast path (the explicit
Ramamoorthi-Hanrahan formulas, the exact quadratic form), whose numbers are those of every stored
probe and filtered environment.

Modules
-------
:mod:`~probegrid.core.sh.basis`
    The basis (convention, constants :data:`K0` .. :data:`K4`, :data:`BASIS_SCALE`), indexing,
    :func:`sh_basis`, :func:`evaluate`.
:mod:`~probegrid.core.sh.clampedcosine`
    The clamped cosine's band factors :data:`A_HAT` / :func:`clamped_cosine_factors` and the
    irradiance (:func:`irradiance`, :func:`irradiance_coefficients`).
:mod:`~probegrid.core.sh.projection`
    :func:`project_cube`, :func:`project_samples`, :func:`project_equirect`.
:mod:`~probegrid.core.sh.rotation`
    :func:`rotate`, :func:`rotation_matrix`, :func:`rotate_y`, :func:`rotation_y`.
:mod:`~probegrid.core.sh.quadratic`
    A band-0-2 function as a quadratic form on the sphere; its Lagrangian dual
    (:func:`eigen_form`, :func:`dual_maximiser`).
:mod:`~probegrid.core.sh.minimum`
    :func:`min_over_sphere`.
:mod:`~probegrid.core.sh.windowing`
    :func:`window_factors`, :func:`window`, :func:`auto_window` (hanning, lanczos, gauss).
:mod:`~probegrid.core.sh.diffusemap`
    :func:`diffuse_cube`, the diffuse (irradiance / pi) map of coefficients.
:mod:`~probegrid.core.sh.dering`
    Per-probe deringing of a grid's band-0-2 SH (imported as ``probegrid.core.sh.dering``).

Non-finite values
-----------------
The projections and :func:`min_over_sphere` / :func:`auto_window` **raise** ``ValueError`` on
nan / inf input (a single bad texel would otherwise poison all coefficients silently). The
pointwise functions (:func:`sh_basis`, :func:`evaluate`, :func:`irradiance`,
:func:`diffuse_cube`, :func:`window`, :func:`rotate`) **propagate** nan / inf by IEEE
arithmetic, without warnings.

References
----------
* R. Ramamoorthi, P. Hanrahan, "An Efficient Representation for Irradiance Environment Maps",
  SIGGRAPH 2001 (basis constants, ``A_l``, eq. 13 quadratic form).
* P.-P. Sloan, "Stupid Spherical Harmonics (SH) Tricks", GDC 2008 (windowing, rotation).
* Filament (Google), ``libs/ibl`` ``CubemapSH``: one SH implementation with a 3-band fast path.
"""

from __future__ import annotations

from probegrid.core.sh.basis import (
    BAND_OF,
    BASIS_SCALE,
    K0,
    K1,
    K2,
    K3,
    K4,
    MAX_BANDS,
    NUM_BANDS,
    NUM_COEFFS,
    band_of,
    bands_of,
    basis_description,
    evaluate,
    num_coeffs,
    sh_basis,
    sh_index,
    sh_lm,
)
from probegrid.core.sh.clampedcosine import (
    A_HAT,
    clamped_cosine_factors,
    irradiance,
    irradiance_coefficients,
)
from probegrid.core.sh.diffusemap import diffuse_cube
from probegrid.core.sh.minimum import min_over_sphere
from probegrid.core.sh.projection import project_cube, project_equirect, project_samples
from probegrid.core.sh.quadratic import dual_maximiser, eigen_form
from probegrid.core.sh.rotation import rotate, rotate_y, rotation_matrix, rotation_y
from probegrid.core.sh.windowing import WindowKind, auto_window, window, window_factors

__all__ = [
    "A_HAT",
    "BAND_OF",
    "BASIS_SCALE",
    "K0",
    "K1",
    "K2",
    "K3",
    "K4",
    "MAX_BANDS",
    "NUM_BANDS",
    "NUM_COEFFS",
    "WindowKind",
    "auto_window",
    "band_of",
    "bands_of",
    "basis_description",
    "clamped_cosine_factors",
    "diffuse_cube",
    "dual_maximiser",
    "eigen_form",
    "evaluate",
    "irradiance",
    "irradiance_coefficients",
    "min_over_sphere",
    "num_coeffs",
    "project_cube",
    "project_equirect",
    "project_samples",
    "rotate",
    "rotate_y",
    "rotation_matrix",
    "rotation_y",
    "sh_basis",
    "sh_index",
    "sh_lm",
    "window",
    "window_factors",
]
