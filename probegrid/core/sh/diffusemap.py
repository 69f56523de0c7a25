"""Diffuse (irradiance / pi) cube maps evaluated from spherical-harmonic coefficients.

A *diffuse map* holds ``E(n) / pi`` at each texel direction ``n``: the outgoing radiance of a
white Lambertian surface (the project's diffuse-map convention), so a constant environment of
radiance ``L`` gives ``L`` everywhere (the white furnace). ``E`` is the SH irradiance of
:mod:`probegrid.core.sh.clampedcosine`, optionally after an anti-ringing window
(:mod:`probegrid.core.sh.windowing`). Filters that project a cube and report their error are in
:mod:`probegrid.core.diffuse`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import SHWindow
from probegrid.core import cubemap as cm
from probegrid.core.sh.basis import NUM_BANDS, check_coeffs, evaluate
from probegrid.core.sh.clampedcosine import irradiance_coefficients
from probegrid.core.sh.windowing import apply_window_option, check_window_option

__all__ = ["diffuse_cube"]


def diffuse_cube(
    L: ArrayLike,
    size: int,
    *,
    window: SHWindow = "none",
    width: float | None = None,
    bands: int = NUM_BANDS,
) -> NDArray[np.float32]:
    """Diffuse (irradiance / pi) cube map from radiance coefficients.

    Each texel holds ``E(n) / pi`` at its centre direction ``n``.

    Parameters
    ----------
    L : (bands^2, C) or (bands^2,) float
        Radiance coefficients.
    size : int
        Face size in texels.
    window : {"none", "hanning", "lanczos", "gauss", "auto"}
        Anti-ringing window applied to ``L`` first (see :func:`probegrid.core.sh.window`);
        ``"auto"`` uses :func:`probegrid.core.sh.auto_window` with a Hanning window (``width``
        must then be None).
    width : float, optional
        Window width, required for "hanning", "lanczos" and "gauss".
    bands : int

    Returns
    -------
    (6, size, size, C) float32 (or (6, size, size, 1) for a (bands^2,) input)
    """
    check_window_option(window)
    c = check_coeffs(L, bands, "L")
    if c.ndim == 1:
        c = c[:, None]
    if c.ndim != 2:
        k = c.shape[0]
        raise ValueError(f"L must have shape ({k}, C) or ({k},), got {c.shape}.")
    c = apply_window_option(c, window, width, bands=bands)
    dirs = cm.texel_directions(size)
    return (evaluate(irradiance_coefficients(c, bands=bands), dirs, bands=bands)
            / np.pi).astype(np.float32)
