"""The environment filter as a function on arrays: one HDR environment in; its diffuse map, GGX
specular chain, SH coefficients, DFG lookup table and quality figures out.

:func:`filter_environment` takes an environment image in any layout
:mod:`probegrid.core.layouts` knows (or the six faces as one ``(6, n, n, C)`` array), checks it
for non-finite pixels (an error with their count unless ``clamp`` is given), sets negative
pixels to 0 (``keep_negative`` keeps them; both counted), resamples it to a cube without
aliasing and computes

* the diffuse map (irradiance / pi) by the exact clamped-cosine integral or through the SH
  coefficients (:mod:`probegrid.core.diffuse`),
* the GGX specular mip chain, level ``k`` at perceptual roughness ``k / (levels - 1)``
  (:mod:`probegrid.core.specular`; Babylon.js' chain for ``format="gltf"``,
  :mod:`probegrid.export.gltf_ibl`, Filament's for ``format="filament"``,
  :mod:`probegrid.export.filament`); by default, for cubes up to 128^2, the exact diffuse map
  and every GGX level are one pass of dense sums over every input texel
  (:func:`probegrid.core.specular.symmetric_zonal_sums`; level 1's far field over 2x2 merged
  texels, ``far_field``),
* the radiance SH coefficients (9 by default, ``bands^2`` with ``sh_bands``;
  :mod:`probegrid.core.sh`) and the minimum irradiance they imply,
* the split-sum DFG lookup table (:mod:`probegrid.core.dfg`; ``dfg_lut=`` takes a cached one),

then applies the seam export mode to every map and level and measures the quality figures
(each map's energy against the input's, the seam scores). It reads and writes no file:
:mod:`probegrid.jobs.filter` reads the input files and writes the maps, ``sh.json``, the LUT,
the previews and the manifest from the :class:`FilteredEnvironment` returned. An all-black
input is legitimate: its maps are black and its quality figures finite (energy ratios 1).

Threads: ``workers`` of them (default: the process's cores,
:func:`probegrid._machine.available_cores`) share the dense sums; with more than one, the
resampling runs in a second thread while the main one loads the next stages' modules and
tables, and a separate diffuse sum beside the GGX chain. Each output texel is one thread's sum,
so the results do not depend on the number of threads.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._machine import available_cores
from probegrid._types import Layout
from probegrid.core.cubemap import downsample, mip_sizes, solid_angle_integral
from probegrid.filter.settings import (
    DEFAULT_MAX_SIZE,
    FilterSettings,
    check_settings,
    default_cube_size,
    diffuse_source_size,
)

__all__ = ["FilteredEnvironment", "Progress", "energy_ratio", "filter_environment"]

#: A progress callback: one line of text per stage.
Progress = Callable[[str], None]


@dataclass(frozen=True, kw_only=True, eq=False)
class FilteredEnvironment:
    """What :func:`filter_environment` computed: the maps as arrays and the facts a manifest
    records. Cubes are ``(6, n, n, C)`` float32 in the face order of
    :mod:`probegrid.core.cubemap`.

    Attributes
    ----------
    cube : (6, n, n, C) float32
        The input resampled (negative values set to 0 unless kept, non-finite ones clamped).
    diffuse : (6, d, d, C) float32
        Irradiance / pi.
    specular : list of (6, n_k, n_k, C) float32
        The GGX chain, level ``k`` at perceptual roughness ``roughness[k]``; level 0 the cube.
    diffuse_export, specular_export
        The same maps with the seam export mode applied (``(n + 2)^2`` faces for ``border``):
        what the output files hold.
    sh : (bands^2, C) float
        Radiance SH coefficients ``L_lm`` (:mod:`probegrid.core.sh` order).
    sh9 : (9, C) float
        Band 2 of them (the consumers' and the glTF light's; ``sh`` itself at 3 bands).
    sh_min_irradiance, sh_min_irradiance_direction : (C,) float, (C, 3) float
        The minimum over the sphere of the irradiance the coefficients imply (not divided by
        pi) and where each channel reaches it.
    sh_window : dict
        The SH diffuse map's window (``{"window": "none"}`` for the exact method), as the
        manifest records it.
    dfg_lut : (L, L, 2) float32
        Split-sum ``(A, B)``; x = N.V (columns), y = perceptual roughness (rows).
    layout : str
        The input's layout (detected for ``auto``).
    source_size : (int, int)
        The input's width and height (of one face for six faces).
    nonfinite, negative : int
        Non-finite values replaced (with ``clamp``) and negative values found.
    cube_size, diffuse_source_size : int
        The cube's face size and the face size the exact diffuse sum read.
    roughness : list of float
        Perceptual roughness per specular level.
    specular_method : str
        How the chain was computed, in words.
    energy : dict
        ``{"diffuse": ratio, "specular": [ratio per level]}``: each map's solid-angle integral
        over the input's (:func:`energy_ratio`; 1 for a correct filter).
    seam_score : dict
        ``{"diffuse": score, "specular": [...]}`` of :func:`probegrid.core.seams.seam_score`
        for the exported maps (the unbordered ones for ``border``).
    timings : dict
        Seconds per stage: ``read`` (checks and resampling), ``sh``, ``specular``, ``diffuse``
        (0 when one pass computed both), ``dfg``.
    """

    cube: NDArray[np.float32]
    diffuse: NDArray[np.float32]
    specular: list[NDArray[np.float32]]
    diffuse_export: NDArray[np.float32]
    specular_export: list[NDArray[np.float32]]
    sh: NDArray[np.floating]
    sh9: NDArray[np.floating]
    sh_min_irradiance: NDArray[np.floating]
    sh_min_irradiance_direction: NDArray[np.floating]
    sh_window: dict[str, Any]
    dfg_lut: NDArray[np.float32]
    layout: str
    source_size: tuple[int, int]
    nonfinite: int
    negative: int
    negative_action: str
    cube_size: int
    diffuse_source_size: int
    roughness: list[float]
    specular_method: str
    energy: dict[str, Any]
    seam_score: dict[str, Any]
    timings: dict[str, float]

    @property
    def levels(self) -> int:
        """Number of specular levels."""
        return len(self.specular)


def energy_ratio(out: NDArray[np.floating], ref: NDArray[np.floating]) -> float:
    """Ratio of the solid-angle integrals (summed over channels) of two cubes of any sizes.

    A diffuse map (irradiance / pi) and every level of a normalised specular filter integrate to
    the same value as the radiance they came from (the kernels are symmetric and normalised), so
    this ratio is 1 for a correct filter, and 1 for a black input with a black output (0 of 0
    lost; the manifest's quality figures stay finite).
    """
    return _integral_ratio(float(solid_angle_integral(out).sum()),
                           float(solid_angle_integral(ref).sum()))


def _integral_ratio(o: float, r: float) -> float:
    """``o / r``, and 1 for a black reference with a black output (see :func:`energy_ratio`)."""
    if r == 0.0:  # a black input: a black output kept all of its (zero) energy
        if o != 0.0:
            raise ValueError("a filter made light out of a black environment")
        return 1.0
    return o / r


def filter_environment(
    environment: ArrayLike,
    *,
    settings: FilterSettings | None = None,
    progress: Progress | None = None,
    workers: int | None = None,
    dfg_lut: Callable[[int], NDArray[np.float32]] | None = None,
    name: str = "the environment",
) -> FilteredEnvironment:
    """Filter one HDR environment; see the module docstring.

    Parameters
    ----------
    environment : (H, W, C) or (6, n, n, C) float
        Radiance: an image in ``settings.layout`` (``auto``: detected from its aspect ratio),
        or the six faces (layout ``auto`` or ``faces``).
    settings : FilterSettings, optional
        Every option (those of the output files are checked too, as their combinations decide
        what is computed: ``format="gltf"`` takes Babylon's chain, ``"filament"`` Filament's).
    progress : callable, optional
        Receives one line per stage.
    workers : int, optional
        Threads (default: the process's cores); the results do not depend on it.
    dfg_lut : callable, optional
        ``size -> (size, size, 2)`` table; default :func:`probegrid.core.dfg.dfg_lut` (the
        command passes :func:`probegrid.usercache.dfg_lut`, the same bits cached per machine).
    name : str
        How messages name the input (the command gives its file).

    Raises
    ------
    ValueError
        With a one-line message for settings that cannot work together, a bad input (its
        shape, layout or non-finite values) or a cube size the chosen chain cannot take.
    """
    from probegrid.core import layouts

    settings = settings or FilterSettings()
    check_settings(settings)
    if workers is None:
        workers = available_cores()
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    workers = int(workers)
    say: Progress = progress or (lambda _m: None)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    source = np.asarray(environment, dtype=np.float32)
    del environment  # (a caller that passes the image on keeps no copy alive: freed once resampled)
    in_layout = _input_layout(source, settings.layout)
    source, nonfinite, negative = _checked_radiance(source, settings, name, say)
    source_wh = (int(source.shape[-2]), int(source.shape[-3]))
    if settings.size:
        n = settings.size
        why = "--size"
    else:
        n = default_cube_size(source.shape[-3], source.shape[-2], in_layout)
        why = (f"default: the input's resolution rounded down to a power of two, at most "
               f"{DEFAULT_MAX_SIZE}; --size to choose")
    diffuse_source_size(n, settings.diffuse_source_size)  # a bad value is refused before work
    say(f"resampling {in_layout} {source.shape[-2]}x{source.shape[-3]} to a {n}^2 cube ({why})")

    # the resampling runs in a second thread while this one loads the modules of the next
    # stages and builds the tables of the dense sums (input-independent, cached per process)
    if workers > 1:
        with ThreadPoolExecutor(max_workers=1) as pool:
            resampled = pool.submit(layouts.to_cube, source, cast(Layout, in_layout), n)
            try:
                plan = _plan(n, settings)
            finally:
                cube = resampled.result()  # (its error first, if both failed)
    else:
        cube = layouts.to_cube(source, cast(Layout, in_layout), n)
        plan = _plan(n, settings)
    del source
    timings["read"] = time.perf_counter() - t0

    from probegrid.core import lobes, seams, sh, specular

    t = time.perf_counter()
    bands = settings.sh_bands
    coeffs = sh.project_cube(cube, bands=bands)
    # band 2, what sh.json's consumers and the glTF light take (the same projection at 3 bands)
    sh9 = coeffs if bands == 3 else sh.project_cube(cube)
    irr_min, irr_min_dir = sh.min_over_sphere(sh.irradiance_coefficients(coeffs, bands=bands),
                                              bands=bands)
    timings["sh"] = time.perf_counter() - t

    levels, diffuse_source = plan.levels, plan.diffuse_source
    say(f"diffuse {settings.diffuse_size}^2 ({settings.diffuse_method}"
        + (f" from the {diffuse_source}^2 box mip" if settings.diffuse_method == "exact"
           and diffuse_source != n else "") + ") and GGX specular "
        f"chain: {levels} levels from {n}^2")
    sh_window: dict[str, Any] = {"window": "none"}

    def diffuse_stage() -> tuple[NDArray[np.float32], Any, float]:
        from probegrid.core import diffuse

        t = time.perf_counter()
        if settings.diffuse_method == "exact":
            src = cube
            while src.shape[1] > diffuse_source:  # the box mip it reads
                src = downsample(src)
            if src.shape[1] > specular.DENSE_CHAIN_MAX:
                d = diffuse.diffuse_exact(src, settings.diffuse_size)
            else:  # the same sum through the cube's symmetries; beside the chain up to 128^2
                d = specular.symmetric_zonal_sums(
                    src, [specular.ZonalOutput(settings.diffuse_size, "cosine")],
                    workers=1 if n <= 128 else workers)[0]
            return d, None, time.perf_counter() - t
        d, inf = diffuse.diffuse_sh(cube, settings.diffuse_size, window=settings.sh_window,
                                    width=settings.sh_window_width, bands=bands)
        return d, inf, time.perf_counter() - t

    if plan.dense:
        # one pass of dense sums over every input texel: the diffuse map and every GGX level
        # (exact), the cube's symmetries shared, the blocks split between the threads
        t = time.perf_counter()
        diff, *rest = specular.symmetric_zonal_sums(cube, plan.outputs, workers=workers,
                                                    far_field=True)
        spec = [cube.copy(), *rest]
        info = None
        timings["specular"] = time.perf_counter() - t
        timings["diffuse"] = 0.0  # (in the specular figure: one pass computed both)
    else:
        diff, info, spec = _separate_stages(cube, settings, levels, diffuse_stage, timings,
                                            workers)
    if info is not None:
        sh_window = {
            "window": info.window,
            "width": info.width if np.isfinite(info.width) else None,
            "min_irradiance_over_pi_after_window": [float(x) for x in info.minimum],
            "coefficients_after_window": [[float(x) for x in row] for row in info.coefficients],
        }

    t = time.perf_counter()
    if dfg_lut is None:
        from probegrid.core import dfg

        dfg_lut = dfg.dfg_lut
    lut = dfg_lut(settings.lut_size)
    timings["dfg"] = time.perf_counter() - t

    cube_integral = float(solid_angle_integral(cube).sum())  # once, not once per level

    def ratio(x: NDArray[np.float32]) -> float:
        return _integral_ratio(float(solid_angle_integral(x).sum()), cube_integral)

    energy = {"diffuse": ratio(diff), "specular": [ratio(lv) for lv in spec]}
    diff_out = seams.apply_seam_mode([diff], settings.seam)[0]
    spec_out = seams.apply_seam_mode(list(spec), settings.seam)
    seam_scores = {
        "diffuse": float(seams.seam_score(diff_out if settings.seam != "border" else diff)),
        "specular": [float(seams.seam_score(lv)) for lv in
                     (spec_out if settings.seam != "border" else spec)],
    }
    if settings.format == "gltf":
        from probegrid.export import gltf_ibl

        roughness = [float(np.sqrt(a)) for a in gltf_ibl.babylon_alphas(n)]
    elif settings.format == "filament":
        from probegrid.export import filament

        roughness = [float(r) for r in filament.filament_roughness(levels)]
    else:
        roughness = [float(r) for r in lobes.level_roughness(np.arange(levels), levels)]
    return FilteredEnvironment(
        cube=cube, diffuse=diff, specular=list(spec), diffuse_export=diff_out,
        specular_export=spec_out, sh=coeffs, sh9=sh9, sh_min_irradiance=irr_min,
        sh_min_irradiance_direction=irr_min_dir, sh_window=sh_window, dfg_lut=lut,
        layout=in_layout, source_size=source_wh, nonfinite=nonfinite, negative=negative,
        negative_action=("kept" if settings.keep_negative and settings.clamp is None
                         else "set to 0"),
        cube_size=n, diffuse_source_size=diffuse_source, roughness=roughness,
        specular_method=("dense sums over every input texel (the far field of lobes narrower "
                         "than alpha 0.06 over 2x2 merged texels)" if plan.dense
                         else settings.specular_method),
        energy=energy, seam_score=seam_scores, timings=timings,
    )


def _input_layout(source: NDArray[np.float32], layout: str) -> str:
    """The layout of ``source``: six faces for a ``(6, n, n, C)`` array, ``layout`` or the one
    its aspect ratio tells for an image; a ``ValueError`` for any other shape."""
    from probegrid.core import layouts

    if source.ndim == 4:
        if source.shape[0] != 6 or source.shape[1] != source.shape[2]:
            raise ValueError("six faces must be a (6, n, n, C) array of square faces, got shape "
                             f"{source.shape}")
        if layout not in ("auto", "faces"):
            raise ValueError(f"six faces need layout 'auto' or 'faces', got {layout!r}")
        return "faces"
    if source.ndim != 3:
        raise ValueError("an environment is an (H, W, C) image or six (n, n, C) faces, got shape "
                         f"{source.shape}")
    if layout == "faces":
        raise ValueError("layout 'faces' needs six faces (+X, -X, +Y, -Y, +Z, -Z)")
    return layouts.detect_layout(source.shape[0], source.shape[1]) if layout == "auto" else layout


def _checked_radiance(source: NDArray[np.float32], settings: FilterSettings, name: str,
                      say: Progress) -> tuple[NDArray[np.float32], int, int]:
    """``source`` with non-finite values clamped (``clamp``; an error naming their pixels
    otherwise) and negative ones set to 0 (unless ``keep_negative``); returns it, the number of
    non-finite values and that of negative ones."""
    from probegrid import imageio

    bad = int(np.count_nonzero(~np.isfinite(source)))
    if bad:
        if settings.clamp is None:
            pixels = imageio.count_nonfinite(source)
            raise ValueError(
                f"{name}: {pixels} pixels have non-finite values (NaN or inf); "
                "pass --clamp to replace them"
            )
        say(f"replacing {bad} non-finite values (NaN -> 0, inf -> clamp)")
    negative = int(np.count_nonzero(source < 0))
    if settings.clamp is not None:
        source = imageio.clamp_radiance(source, settings.clamp)
        if negative:
            say(f"note: {negative} negative values set to 0 (radiance is never negative)")
    elif negative and settings.keep_negative:
        say(f"note: {negative} negative values kept (--keep-negative)")
    elif negative:
        source = np.maximum(source, np.float32(0.0))
        say(f"note: {negative} negative values set to 0 (radiance is never negative; "
            "--keep-negative keeps them)")
    return source, bad, negative


@dataclass(frozen=True)
class _Plan:
    """The chain's shape for a cube size: levels, the diffuse sum's source size, whether one
    pass of dense sums computes everything (and its outputs)."""

    levels: int
    diffuse_source: int
    dense: bool
    outputs: Sequence[Any]


def _engine_chain(fmt: str) -> Any:
    """The module whose ``mip_count`` and ``specular_chain`` give an engine format's chain
    (Babylon's for ``gltf``, Filament's for ``filament``), or None for probegrid's own."""
    if fmt == "gltf":
        from probegrid.export import gltf_ibl

        return gltf_ibl
    if fmt == "filament":
        from probegrid.export import filament

        return filament
    return None


def _plan(n: int, settings: FilterSettings) -> _Plan:
    """The chain's shape for an ``n``^2 cube; loads the modules of the filter stages and builds
    the dense sums' tables (a ``ValueError`` for a cube size the chosen chain cannot take)."""
    from probegrid.core import lobes, specular

    # the full chain by default; a cube that is not a power of two gets its level 0
    default_levels = None if n & (n - 1) == 0 else 1
    levels = len(mip_sizes(n, settings.specular_levels or default_levels))
    engine = _engine_chain(settings.format)
    if engine is not None:
        levels = engine.mip_count(n)  # ValueError unless n is a power of two >= 32
    diffuse_source = diffuse_source_size(n, settings.diffuse_source_size)
    dense = (n <= specular.DENSE_CHAIN_MAX and n & (n - 1) == 0
             and engine is None and settings.specular_method == "tiered"
             and settings.diffuse_method == "exact" and diffuse_source == n)
    outputs: list[Any] = []
    if dense:
        outputs = [specular.ZonalOutput(settings.diffuse_size, "cosine")] + [
            specular.ZonalOutput(s, "ggx", float(lobes.roughness_to_alpha(
                lobes.level_roughness(k, levels))))
            for k, s in enumerate(mip_sizes(n, levels)) if k]
        specular.prepare_zonal_sums(n, outputs)
    return _Plan(levels, diffuse_source, dense, outputs)


def _separate_stages(cube: NDArray[np.float32], settings: FilterSettings, levels: int,
                     diffuse_stage: Callable[[], Any], timings: dict[str, float], workers: int
                     ) -> tuple[NDArray[np.float32], Any, list[Any]]:
    """The diffuse map and the specular chain by their own functions (every case but one pass of
    dense sums); returns (diffuse, SH window info or None, chain)."""
    from probegrid.core import specular

    n = cube.shape[1]
    spec_kwargs: dict[str, Any] = {"levels": levels, "method": settings.specular_method}
    if settings.samples is not None:
        spec_kwargs["samples"] = settings.samples
    # the diffuse sum runs in a second thread beside the GGX chain (both spend their time in
    # numpy calls that release the GIL; the chain limits BLAS to one thread), for cubes up to
    # 128^2: the chain of a larger cube needs the memory (peak RSS 530 vs 480 MB at 256^2)
    with ThreadPoolExecutor(max_workers=1) as pool:
        diffuse_future = pool.submit(diffuse_stage) if n <= 128 and workers > 1 else None
        t = time.perf_counter()
        engine = _engine_chain(settings.format)
        if engine is None:
            spec = specular.ggx_prefilter(cube, **spec_kwargs)
        else:
            spec = engine.specular_chain(cube)  # the engine's own mip -> roughness mapping
        timings["specular"] = time.perf_counter() - t
        if n > 128:  # one cube of this size: its plans are not reused, free them for the rest
            specular.clear_caches()
        diff, info, timings["diffuse"] = (diffuse_future.result() if diffuse_future is not None
                                          else diffuse_stage())
    return diff, info, spec
