"""Diffuse (irradiance / pi) environment filters: exact clamped-cosine sum and band-2 SH.

A diffuse map holds, at each texel direction ``n``, ``E(n) / pi``: the outgoing radiance of a
white Lambertian surface with normal ``n`` lit by the environment (constant ``L`` in, ``L`` out).

Exact (:func:`diffuse_exact`)
-----------------------------
``E(n) / pi = (1 / pi) sum_q L_q max(0, n . w_q) dOmega_q`` over *every* source texel ``q``
(centre ``w_q``, exact solid angle from :func:`probegrid.core.cubemap.texel_solid_angles`): the
midpoint rule on the piecewise-constant input, no normalisation. It is the product of the
``(6 size^2, 6 n^2)`` clamped-cosine matrix with the ``(6 n^2, C)`` weighted radiance. For a
power-of-two input of at least 8^2 the same sum is computed hierarchically
(:func:`probegrid.core.clampedcos.clamped_cosine_sum`: blocks wholly in front of a normal add
their exact vector moment, blocks behind nothing, only blocks on the horizon texel by texel;
equal to the dense sum to float64 rounding, about 30 x fewer operations at 128^2). Other sizes
use the dense product in float64 chunks of output texels
(:func:`probegrid.core.specular.zonal_convolution`), about three ``(rows, 6 n^2)`` float64 blocks of
``chunk_bytes`` alive; its cost is ``36 size^2 n^2`` multiply-adds.

Option ``source_size``: box-filter the input down to ``source_size`` first (solid-angle-weighted
mips, :func:`probegrid.core.cubemap.downsample`). The clamped cosine is smooth except at the horizon,
so this adds only the midpoint-rule error of a coarser grid: it is second order in the coarse
texel size ``h`` for smooth radiance, but first order in ``h`` for a bright texel whose position
inside its coarse texel is lost (a sun). Measured on the two real HDRs, 32^2 output from a 128^2
cube: ``source_size=64`` gives mean 1.6e-4 and max 0.4 % (venice) / 2.2 % (studio's tiny
softboxes) relative error, at a quarter of the cost; ``source_size=32``: mean 5e-4 / 1.2e-3, max
1.4 % / 16 % (``tests/test_diffuse.py`` checks the 64 -> 32 case).

SH (:func:`diffuse_sh`)
-----------------------
Any band count with ``bands`` (:mod:`probegrid.core.sh`). Each count's error is that of
the exact projection (projecting the cube equals projecting every pixel of the lat-long input to
1.001 x): against the exact sum on venice, 3 bands 1.85 % mean / 20 % max, 5 bands 0.56 % /
8.6 %, 9 bands 0.14 % / 3.3 %; on studio (small bright softboxes in a dark room) 27 % / 700 %,
15 % / 360 % and 5.9 % / 156 %. SH is the wrong tool for small bright sources: its error
falls only slowly with the band count (the clamped cosine's ``A_l`` decay as ``l^(-5/2)``), and
truncation rings below zero; use :func:`diffuse_exact`, which is exact and cheap.

Band-0-2 spherical harmonics (:mod:`probegrid.core.sh`, Ramamoorthi & Hanrahan 2001): project the
input exactly, optionally window the coefficients against ringing (Sloan 2008), and evaluate
``E / pi``. Band 2 captures the clamped cosine only approximately (its ``l > 2`` tail is dropped:
up to 9.4 % of the peak for a single directional light, R&H 2001), so a strong sun costs
accuracy; windowing removes ringing (negative lobes) at the price of more error. The result's
``info`` reports the minimum of ``E / pi`` over the whole sphere (not just texel centres): a
negative value is a visible defect (black or inverted colours) and is flagged.

Measured SH-vs-exact relative error (32^2 from 128^2; ``benchmarks/bench_filter.py``, asserted
in ``tests/test_diffuse.py``): venice (strong sun) mean 1.9 %, max 20 %; studio (softboxes in a
dark room) mean 27 %, max 690 %, and its raw projection goes negative (E/pi down to -0.055);
the auto window makes it non-negative at mean 28 %, max 780 %. Band 2 cannot meet a 1 % mean /
3 % max target on either scene: use :func:`diffuse_exact` where accuracy matters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import SHWindow
from probegrid.core import sh
from probegrid.core.clampedcos import clamped_cosine_sum
from probegrid.core.cubemap import check_cube, downsample, texel_directions
from probegrid.core.specular import zonal_convolution

__all__ = ["DiffuseSHInfo", "SHWindow", "diffuse_exact", "diffuse_sh"]


_CHUNK_BYTES = 32 * 2**20


def _finite_faces(faces: ArrayLike) -> NDArray[np.float32]:
    """The input cube ``(6, n, n, C)`` after :func:`check_cube`, refused unless finite."""
    src = check_cube(faces, name="faces")
    if not np.all(np.isfinite(src)):
        raise ValueError("faces must be finite (no nan or inf radiance).")
    return src


def _clamped_cosine_over_pi(c: NDArray[np.float64]) -> NDArray[np.float64]:
    np.maximum(c, 0.0, out=c)
    c *= 1.0 / np.pi
    return c


def diffuse_exact(
    faces: ArrayLike,
    size: int,
    *,
    source_size: int | None = None,
    chunk_bytes: int = _CHUNK_BYTES,
) -> NDArray[np.float32]:
    """Exact diffuse map: the clamped-cosine sum over every source texel.

    Parameters
    ----------
    faces : (6, n, n, C) float
        Input radiance (finite).
    size : int
        Output face size.
    source_size : int, optional
        Box-filter the input to this face size first (``n / 2^j``); default: use every input
        texel (exact). See the module docstring for the error this introduces.
    chunk_bytes : int
        Size of one float64 ``(rows, 6 n^2)`` block; peak memory is about three of them.

    Returns
    -------
    (6, size, size, C) float32
        ``E / pi``; a constant environment ``L`` gives ``L`` up to the midpoint-rule error of
        the input grid at the horizon kink (2e-4 relative at n = 16, 5e-5 at 32, 1.3e-5 at 64).
    """
    src = _finite_faces(faces)
    if not isinstance(chunk_bytes, (int, np.integer)) or chunk_bytes < 1:
        raise ValueError(f"chunk_bytes must be a positive integer, got {chunk_bytes!r}.")
    if source_size is not None:
        n = src.shape[1]
        ok = (isinstance(source_size, (int, np.integer)) and not isinstance(source_size, bool)
              and 1 <= source_size <= n and n % source_size == 0
              and (n // source_size) & (n // source_size - 1) == 0)
        if not ok:
            raise ValueError(f"source_size must be the input size {n} divided by a power of two, "
                             f"got {source_size!r}.")
        while src.shape[1] > source_size:
            src = downsample(src)
    m = src.shape[1]
    if m >= 8 and m & (m - 1) == 0:  # the same sum, hierarchically (probegrid.core.clampedcos)
        irr = clamped_cosine_sum(src, texel_directions(int(size)).reshape(-1, 3))
        return (irr / np.pi).reshape(6, size, size, -1).astype(np.float32)
    out = zonal_convolution(src, _clamped_cosine_over_pi, size, normalize=False,
                            chunk_bytes=int(chunk_bytes))
    return out.astype(np.float32)


@dataclass(frozen=True)
class DiffuseSHInfo:
    """What :func:`diffuse_sh` computed besides the cube.

    Attributes
    ----------
    coefficients : (bands^2, C) float64
        Radiance SH coefficients actually used (after the window).
    projected : (bands^2, C) float64
        Radiance SH coefficients of the input, before windowing.
    window : str
        The window kind applied.
    width : float
        Its width (``inf`` for no window).
    minimum : (C,) float64
        Minimum of ``E / pi`` over the whole sphere, per channel.
    minimum_direction : (C, 3) float64
        Where it is reached.
    negative : bool
        True when some channel's minimum is negative: the map has a visible ringing defect.
    """

    coefficients: NDArray[np.float64]
    projected: NDArray[np.float64]
    window: str
    width: float
    minimum: NDArray[np.float64]
    minimum_direction: NDArray[np.float64]
    negative: bool


def diffuse_sh(
    faces: ArrayLike,
    size: int,
    *,
    window: SHWindow = "none",
    width: float | None = None,
    bands: int = 3,
) -> tuple[NDArray[np.float32], DiffuseSHInfo]:
    """Diffuse map from spherical harmonics (bands 0-2 by default, any count with ``bands``).

    Parameters
    ----------
    faces : (6, n, n, C) float
        Input radiance (finite).
    size : int
        Output face size.
    window : {"none", "hanning", "lanczos", "gauss", "auto"}
        Anti-ringing window (:func:`probegrid.core.sh.window`); ``"auto"`` picks the gentlest Hanning
        window that makes the irradiance non-negative (:func:`probegrid.core.sh.auto_window`).
    width : float, optional
        Window width, required for "hanning", "lanczos" and "gauss"; must be None otherwise.
    bands : int
        Number of SH bands (``bands^2`` coefficients, :mod:`probegrid.core.sh`). The default
        3 is the stored 9-coefficient basis.

    Returns
    -------
    cube : (6, size, size, C) float32
        ``E / pi`` at the texel centres.
    info : DiffuseSHInfo
        Coefficients, the window used and the minimum of ``E / pi`` over the sphere.
    """
    if window not in get_args(SHWindow):
        raise ValueError(f"window must be one of {get_args(SHWindow)}, got {window!r}.")
    if window in ("none", "auto") and width is not None:
        raise ValueError(f"width must be None with window={window!r}.")
    if window in ("hanning", "lanczos", "gauss") and width is None:
        raise ValueError(f"window={window!r} needs a width.")
    src = _finite_faces(faces)
    if not isinstance(size, (int, np.integer)) or isinstance(size, bool) or size < 1:
        raise ValueError(f"size must be a positive integer, got {size!r}.")
    projected = sh.project_cube(src, bands=bands)
    if window == "auto":
        coeffs, used = sh.auto_window(projected, kind="hanning", quantity="irradiance",
                                      bands=bands)
        kind = "hanning"
    elif window == "none":
        coeffs, used, kind = projected, float("inf"), "none"
    else:
        coeffs = sh.window(projected, kind=window, width=float(width), bands=bands)
        used, kind = float(width), window
    cube = sh.diffuse_cube(coeffs, int(size), window="none", bands=bands)
    vmin, dmin = sh.min_over_sphere(sh.irradiance_coefficients(coeffs, bands=bands),
                                    bands=bands)
    vmin = np.atleast_1d(vmin) / np.pi
    info = DiffuseSHInfo(
        coefficients=coeffs,
        projected=projected,
        window=kind,
        width=float(used),
        minimum=vmin,
        minimum_direction=np.atleast_2d(dmin),
        negative=bool(np.any(vmin < 0)),
    )
    return cube, info
