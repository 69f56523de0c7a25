"""``probegrid filter``: one HDR environment in; diffuse, specular, SH, DFG LUT and a manifest out.

The job, in order: read the environment (any layout :mod:`probegrid.core.layouts` knows, or six face
files), check it for non-finite pixels (an error with their count unless ``clamp`` is given),
resample it to a cube without aliasing, and compute

* the diffuse map (irradiance / pi) by the exact clamped-cosine integral or through 9 SH
  coefficients (:mod:`probegrid.core.diffuse`),
* the GGX specular mip chain, level ``k`` at perceptual roughness ``k / (levels - 1)``
  (:mod:`probegrid.core.specular`); by default, for cubes up to 128^2, the exact diffuse map
  and every GGX level are one pass of dense sums over every input texel shared between two
  threads (:func:`probegrid.core.specular.symmetric_zonal_sums`; level 1's far field over
  2x2 merged texels, ``far_field``),
* the radiance SH coefficients (9 by default, ``bands^2`` with ``sh_bands``;
  :mod:`probegrid.core.sh`) and the minimum irradiance they imply,
* the split-sum DFG lookup table (:mod:`probegrid.core.dfg`, cached per machine by
  :mod:`probegrid.usercache`),

then applies the seam export mode to every map and level and writes the maps, ``sh.json``, the
LUT, PNG previews and, last, ``manifest.json``. Option combinations that cannot work and an
output location that cannot be written are refused before any work (:func:`check_settings`,
:func:`probegrid.jobs.staging.staged_output`). Everything is written into a staging folder
beside the output directory and moved into place only when complete, so a failed or
interrupted run leaves the output directory as it was (an earlier output whole) and no
temporary file: a directory with a manifest holds a finished job. The input is resampled in
a second thread while the main one loads the next stages' modules and tables; the maps and
the previews are encoded and flushed to disk by a pool of two threads (a map's six faces by
the same one) while the main thread writes ``sh.json`` and the LUT. An all-black input is
legitimate: its maps are black and its quality figures finite (energy ratios 1).

Negative input pixels are set to 0 and counted (``--keep-negative`` keeps them). The DFG table
depends only on its size and is cached per machine (:mod:`probegrid.usercache`).

The output directory must be new, or hold an earlier output of the same kind (its
``manifest.json`` has the same ``format``): :func:`prepare_output_dir` refuses a probe grid store
(``NAME.probes``, or any directory whose manifest is a store's), an unfinished bake, and a
directory whose ``manifest.json`` belongs to another kind of output or cannot be read, before
anything is computed or written. ``probegrid export`` (:mod:`probegrid.jobs.export`) uses it too.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal, cast, get_args, get_origin, get_type_hints

import numpy as np
from numpy.typing import NDArray

from probegrid._fs import atomic_write_json, fsync_file
from probegrid._types import (
    CubeConvention,
    CubeLayout,
    DiffuseMethod,
    GGXMethod,
    InputLayout,
    Layout,
    MapFormat,
    SeamMode,
    SHWindow,
)
from probegrid._version import __version__
from probegrid.core.conventions import conventions
from probegrid.core.cubemap import downsample, mip_sizes, solid_angle_integral
from probegrid.errors import SettingsError

__all__ = [
    "FILTER_FORMAT",
    "FilterResult",
    "FilterSettings",
    "check_settings",
    "default_cube_size",
    "energy_ratio",
    "prepare_output_dir",
    "run_filter",
]

#: ``format`` of the manifest of a filter output directory.
FILTER_FORMAT = "probegrid.filter"

Progress = Callable[[str], None]


def _option(default: Any, **bounds: float) -> Any:
    """A :class:`FilterSettings` field with its bounds (``ge``, ``le``, ``gt``)."""
    return field(default=default, metadata=bounds)


@dataclass(frozen=True, kw_only=True)
class FilterSettings:
    """Options of ``probegrid filter`` (see ``probegrid filter --help``).

    A frozen dataclass whose every field is checked on construction against its type (a
    ``Literal`` of :mod:`probegrid._types`, an integer, a number or a flag, optionally None)
    and bounds (:class:`probegrid.errors.SettingsError`, naming the field, for a bad value);
    the command line's options are generated from it. (A dataclass, not a pydantic model like
    the bake's settings: the filter command runs in well under a second, and loading pydantic
    and building a model would take a tenth of that.)
    """

    layout: InputLayout = "auto"
    size: int | None = _option(None, ge=1, le=4096)
    diffuse_size: int = _option(32, ge=1, le=1024)
    diffuse_method: DiffuseMethod = "exact"
    diffuse_source_size: int | None = _option(None, ge=1, le=4096)
    specular_levels: int | None = _option(None, ge=1, le=16)
    specular_method: GGXMethod = "tiered"
    samples: int | None = _option(None, ge=1, le=65536)
    sh_bands: int = _option(3, ge=1, le=16)
    sh_window: SHWindow = "none"
    sh_window_width: float | None = _option(None, gt=0)
    format: MapFormat = "exr"
    cube_convention: CubeConvention = "gltf"
    half: bool = True
    output_layout: CubeLayout = "faces"
    seam: SeamMode = "none"
    clamp: float | None = _option(None, gt=0)
    keep_negative: bool = False
    lut_size: int = _option(128, ge=2, le=1024)
    previews: bool = True

    def __post_init__(self) -> None:
        hints = _settings_types()
        for f in fields(self):
            value = _checked(f.name, getattr(self, f.name), hints[f.name], f.metadata)
            object.__setattr__(self, f.name, value)  # (a numpy integer becomes an int)

    def as_dict(self) -> dict[str, Any]:
        """Every field and its value (the manifest's ``settings``)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@lru_cache(maxsize=1)
def _settings_types() -> dict[str, Any]:
    return get_type_hints(FilterSettings)


def _checked(name: str, value: Any, annotation: Any, bounds: Mapping[str, float]) -> Any:
    """``value`` of the field ``name`` checked against its type and bounds (an integer field
    takes any integral number, a number field any real one); a :class:`SettingsError`
    otherwise."""
    kinds = get_args(annotation) if get_origin(annotation) is not Literal else (annotation,)
    kinds = kinds or (annotation,)
    if value is None and type(None) in kinds:
        return None
    literal = next((k for k in kinds if get_origin(k) is Literal), None)
    if literal is not None:
        if isinstance(value, str) and value in get_args(literal):
            return value
        raise SettingsError(name, f"expected one of {', '.join(map(repr, get_args(literal)))}, "
                                  f"got {value!r}")
    if bool in kinds:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        raise SettingsError(name, f"expected true or false, got {value!r}")
    if int in kinds:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise SettingsError(name, f"expected an integer, got {value!r}")
        value = int(value)
    elif float in kinds:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer,
                                                                          np.floating)):
            raise SettingsError(name, f"expected a number, got {value!r}")
        value = float(value)
    if "ge" in bounds and not value >= bounds["ge"]:
        raise SettingsError(name, f"must be >= {bounds['ge']}, got {value!r}")
    if "le" in bounds and not value <= bounds["le"]:
        raise SettingsError(name, f"must be <= {bounds['le']}, got {value!r}")
    if "gt" in bounds and not value > bounds["gt"]:
        raise SettingsError(name, f"must be > {bounds['gt']}, got {value!r}")
    return value


@dataclass
class FilterResult:
    """What a filter run wrote: the output directory and the manifest's content."""

    out_dir: Path
    manifest: dict[str, Any]
    files: list[dict[str, Any]] = field(default_factory=list)

    def summary(self) -> str:
        """A few lines for the terminal: where things are and the quality figures."""
        q = self.manifest["quality"]
        kinds: dict[str, int] = {}
        count = 0
        for f in self.files:
            kinds[f["kind"]] = kinds.get(f["kind"], 0) + 1
            count += len(f["path"]) if isinstance(f["path"], list) else 1
        lines = [
            f"wrote {count + 1} files to {self.out_dir}/: "
            + ", ".join(f"{v} {k} {'map' if k in ('diffuse', 'specular') else 'file'}"
                        + ("s" if v > 1 else "") for k, v in sorted(kinds.items()))
            + ", manifest.json",
            f"  manifest:  {self.out_dir / 'manifest.json'}",
            (
                f"  SH:        {self.out_dir / 'sh.json'}  (min irradiance/pi over the sphere "
                f"{_fmt3(q['sh_min_irradiance_over_pi'])})"
            ),
            (
                f"  energy:    diffuse/input {q['energy']['diffuse']:.4f}, specular/input "
                f"{min(q['energy']['specular']):.4f}..{max(q['energy']['specular']):.4f}"
            ),
        ]
        previews = [f["path"] for f in self.files if f["kind"] == "preview"]
        if previews:
            lines.append("  previews:  " + ", ".join(str(self.out_dir / p) for p in previews))
        return "\n".join(lines)


def _fmt3(v: Sequence[float]) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _manifest_format(file: Path) -> str | None:
    """The ``format`` string of a JSON manifest, or None when it has none or cannot be read."""
    try:
        doc = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    fmt = doc.get("format") if isinstance(doc, dict) else None
    return fmt if isinstance(fmt, str) else None


def prepare_output_dir(
    out_dir: str | os.PathLike[str], output_format: str, *, create: bool = True
) -> Path:
    """Check that ``out_dir`` may receive an output whose manifest has format ``output_format``;
    with ``create``, make it and remove an earlier output's manifest (the new one is written
    last, so an interrupted run leaves none).

    The directory may be new or hold an earlier output of the same format; anything else that
    holds a ``manifest.json`` (a probe grid store, another kind of output, an unreadable file),
    a directory named like a store (``NAME.probes``, ``.probes.partial``, ``.probes.work``) or
    holding an unfinished bake's state is refused with a ``ValueError`` (one sentence), so that
    no output ever overwrites a store.

    Returns
    -------
    Path
        ``out_dir`` as a Path.
    """
    # (the store's names, imported here: the filter command needs nothing else of the store)
    from probegrid.store.names import DONE_FILE, PLAN_FILE, STORE_DIR_SUFFIXES

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output directory {out} exists and is not a directory")
    names = {Path(os.path.abspath(out)).name, out.resolve().name}
    if any(n.endswith(STORE_DIR_SUFFIXES) for n in names) or any(
        (out / f).exists() for f in (PLAN_FILE, DONE_FILE)  # an unfinished bake's state
    ):
        raise ValueError(
            f"output directory {out} is a probe grid store or bake directory (NAME.probes, "
            "NAME.probes.partial or NAME.probes.work); refusing to write into it, choose "
            "another output directory"
        )
    manifest = out / "manifest.json"
    if manifest.exists() or manifest.is_symlink():
        found = _manifest_format(manifest)
        if found != output_format:
            what = ("a probe grid store's" if found == "probegrid.store"
                    else f"a {found!r} output's" if found
                    else "an unreadable or unknown")
            raise ValueError(
                f"output directory {out} holds {what} manifest.json, not an earlier "
                f"{output_format!r} output; refusing to overwrite it, choose another output "
                "directory"
            )
    if create:
        out.mkdir(parents=True, exist_ok=True)
        manifest.unlink(missing_ok=True)  # an interrupted run must not leave an old manifest
    return out


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


#: Largest cube face size chosen by default (a 256^2 chain takes ~2 s and ~300 MB here).
DEFAULT_MAX_SIZE = 256


def default_cube_size(height: int, width: int, layout: str) -> int:
    """Face size used when ``--size`` is not given: the input's own resolution
    (:func:`probegrid.layouts.default_face_size` before its rounding: ``W / 4`` for equirect,
    ``S / pi`` for angular maps, the face size for crosses and faces) rounded *down* to a power
    of two (the tiered GGX chain needs one, and no texel is finer than the input), at most
    :data:`DEFAULT_MAX_SIZE` and at least 1. 1024 x 512 equirect -> 256, 1500 x 750 -> 256,
    512 x 256 -> 128; six 100^2 faces -> 64."""
    from probegrid.core import layouts

    if layout == "faces":
        exact = float(min(height, width))
    else:
        exact = {"equirect": width / 4, "angular": width / np.pi, "hcross": width / 4,
                 "vcross": width / 3}[layout]
        layouts.default_face_size(height, width, layout)  # checks the arguments
    n = 1 << max(0, int(np.floor(np.log2(max(exact, 1.0)))))
    return min(n, DEFAULT_MAX_SIZE)


#: Threads encoding and flushing the output files (on this 2-core machine two keep both cores
#: busy beside the thread writing sh.json and the LUT).
_WRITE_THREADS = 2

#: The exact diffuse sum reads at most this face size by default (the box mip of larger cubes).
DEFAULT_DIFFUSE_SOURCE = 128


def _diffuse_source_size(n: int, requested: int | None) -> int:
    """Face size the exact diffuse sum reads: ``requested`` (``n`` divided by a power of two),
    else ``n`` up to :data:`DEFAULT_DIFFUSE_SOURCE` and that size's box mip of larger cubes.

    Irradiance is band-limited, so the mip changes little: a 32^2 diffuse map from the 128^2 mip
    of a 256^2 cube differs from the sum over all 256^2 texels by 3e-5 / 4e-5 mean and
    0.1 % / 0.55 % max relative (venice / studio, measured), at a third of the time and memory.
    """
    if requested is None:
        if n <= DEFAULT_DIFFUSE_SOURCE or n & (n - 1):
            return n
        return DEFAULT_DIFFUSE_SOURCE
    ratio = n // requested
    if requested > n or n % requested or ratio & (ratio - 1):
        raise ValueError(f"--diffuse-source-size must be the cube size {n} divided by a power "
                         f"of two, got {requested}")
    return requested


def _read_environment(
    paths: Sequence[Path], settings: FilterSettings, progress: Progress
) -> tuple[NDArray[np.float32], str, int, int, tuple[int, int], int]:
    """Read and check the environment and choose the cube size; returns (the image or the six
    faces, layout, nonfinite count, negative count, source width and height (of one face for
    six files), cube face size). :func:`probegrid.core.layouts.to_cube` then resamples it."""
    from probegrid import imageio
    from probegrid.core import layouts

    paths = [Path(p) for p in paths]
    layout = settings.layout
    if len(paths) == 6 and layout in ("auto", "faces"):
        paths = imageio.order_face_files(paths)  # by their names, not the shell's sort
        images = [imageio.read_image(p) for p in paths]
        shapes = {im.shape for im in images}
        if len(shapes) != 1 or images[0].shape[0] != images[0].shape[1]:
            raise ValueError(
                "six face files must be square images of one size, got "
                + ", ".join(f"{im.shape[1]}x{im.shape[0]}" for im in images)
            )
        source = np.stack(images)
        layout = "faces"
    elif len(paths) == 1:
        if layout == "faces":
            raise ValueError("layout 'faces' needs six face files (+X, -X, +Y, -Y, +Z, -Z)")
        source = imageio.read_image(paths[0])
        if layout == "auto":
            layout = layouts.detect_layout(source.shape[0], source.shape[1])
    else:
        raise ValueError(f"give one environment image or six face files, got {len(paths)} files")

    bad = int(np.count_nonzero(~np.isfinite(source)))
    if bad:
        if settings.clamp is None:
            pixels = imageio.count_nonfinite(source)
            raise ValueError(
                f"{paths[0]}: {pixels} pixels have non-finite values (NaN or inf); "
                "pass --clamp to replace them"
            )
        progress(f"replacing {bad} non-finite values (NaN -> 0, inf -> clamp)")
    negative = int(np.count_nonzero(source < 0))
    if settings.clamp is not None:
        source = imageio.clamp_radiance(source, settings.clamp)
        if negative:
            progress(f"note: {negative} negative values set to 0 (radiance is never negative)")
    elif negative and settings.keep_negative:
        progress(f"note: {negative} negative values kept (--keep-negative)")
    elif negative:
        source = np.maximum(source, np.float32(0.0))
        progress(f"note: {negative} negative values set to 0 (radiance is never negative; "
                 "--keep-negative keeps them)")

    if settings.size:
        n = settings.size
        why = "--size"
    else:
        n = default_cube_size(source.shape[-3], source.shape[-2], layout)
        why = (f"default: the input's resolution rounded down to a power of two, at most "
               f"{DEFAULT_MAX_SIZE}; --size to choose")
    _diffuse_source_size(n, settings.diffuse_source_size)  # a bad value is refused before work
    progress(f"resampling {layout} {source.shape[-2]}x{source.shape[-3]} to a {n}^2 cube ({why})")
    return source, layout, bad, negative, (int(source.shape[-2]), int(source.shape[-3])), n


def run_filter(
    env: Sequence[str | os.PathLike[str]] | str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    settings: FilterSettings | None = None,
    *,
    progress: Progress | None = None,
) -> FilterResult:
    """Run the whole filter job; see the module docstring. Returns what was written.

    Raises ``ValueError`` (``probegrid.imageio.ImageError`` for files) with a one-line message
    for bad input, before anything is written to ``out_dir``. Every option combination and the
    output location are checked before any work; the files are written into a staging folder
    moved into place only when complete (:mod:`probegrid.jobs.staging`), so a failure leaves
    ``out_dir`` as it was and no temporary file behind.
    """
    from probegrid.jobs.staging import staged_output

    settings = settings or FilterSettings()
    check_settings(settings)
    paths = [env] if isinstance(env, (str, os.PathLike)) else list(env)
    out = prepare_output_dir(out_dir, FILTER_FORMAT, create=False)  # refuse early
    with staged_output(out, lambda final: prepare_output_dir(final, FILTER_FORMAT,
                                                             create=False)) as stage:
        manifest, files = _filter_into(stage, paths, settings, progress)
    return FilterResult(out, manifest, files)


def check_settings(settings: FilterSettings) -> None:
    """Refuse option combinations that cannot work (one-line ``ValueError``), before any work."""
    if settings.seam == "border" and settings.output_layout != "faces":
        raise ValueError("--seam border writes (n+2)^2 faces, which only --output-layout faces "
                         f"can hold (got --output-layout {settings.output_layout})")
    if settings.samples is not None and settings.specular_method != "fis":
        raise ValueError("--samples applies to --specular-method fis (importance sampling)")
    if (settings.diffuse_method == "sh" and settings.sh_window not in ("none", "auto")
            and settings.sh_window_width is None):
        raise ValueError(f"--sh-window {settings.sh_window} needs --sh-window-width")
    if settings.format == "ktx2" and (settings.output_layout != "faces"
                                      or settings.seam == "border"):
        raise ValueError("--format ktx2 writes cube maps: it needs --output-layout faces and a "
                         "seam mode other than 'border'")
    if settings.cube_convention != "gltf" and settings.format != "ktx2":
        raise ValueError("--cube-convention applies to --format ktx2")
    if settings.format == "gltf" and (settings.output_layout != "faces"
                                      or settings.seam == "border"
                                      or settings.specular_levels is not None
                                      or settings.specular_method != "tiered"):
        raise ValueError("--format gltf writes Babylon's mip chain (down to 16^2, tiered GGX): "
                         "it needs --output-layout faces, no --specular-levels or "
                         "--specular-method and a seam mode other than 'border'")
    if settings.format == "gltf" and settings.size is not None:
        from probegrid.export.gltf_ibl import check_size

        check_size(settings.size)


def _filter_into(
    out: Path, paths: Sequence[str | os.PathLike[str]], settings: FilterSettings,
    progress: Progress | None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Compute everything, then write it into the (staging) directory ``out``; returns the
    manifest and its file list."""
    from probegrid import imageio
    from probegrid.core import layouts

    say: Progress = progress or (lambda _m: None)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    source, in_layout, nonfinite, negative, source_wh, n = _read_environment(
        [Path(p) for p in paths], settings, say)
    # the resampling runs in a second thread while this one loads the modules of the next
    # stages and builds the tables of the dense sums (input-independent, cached per process)
    with ThreadPoolExecutor(max_workers=1) as pool:
        resampled = pool.submit(layouts.to_cube, source, cast(Layout, in_layout), n)
        try:
            from probegrid import usercache
            from probegrid.core import lobes, seams, sh, specular
            from probegrid.export.shforms import sh_forms

            # the full chain by default; a cube that is not a power of two gets its level 0
            default_levels = None if n & (n - 1) == 0 else 1
            levels = len(mip_sizes(n, settings.specular_levels or default_levels))
            if settings.format == "gltf":
                from probegrid.export import gltf_ibl

                levels = gltf_ibl.mip_count(n)  # ValueError unless n is a power of two >= 32
            diffuse_source = _diffuse_source_size(n, settings.diffuse_source_size)
            dense = (n <= specular.DENSE_CHAIN_MAX and n & (n - 1) == 0
                     and settings.format != "gltf" and settings.specular_method == "tiered"
                     and settings.diffuse_method == "exact" and diffuse_source == n)
            if dense:
                outs = [specular.ZonalOutput(settings.diffuse_size, "cosine")] + [
                    specular.ZonalOutput(s, "ggx", float(lobes.roughness_to_alpha(
                        lobes.level_roughness(k, levels))))
                    for k, s in enumerate(mip_sizes(n, levels)) if k]
                specular.prepare_zonal_sums(n, outs)
        finally:
            cube = resampled.result()  # (its error first, if both failed)
    del source
    timings["read"] = time.perf_counter() - t0

    # every map file and preview is encoded in one pool of threads (the encoders, the tone
    # mapping and the flushes release the GIL), each task flushing its files to disk (the
    # staging folder's commit then finds them there); the input's preview, which needs the
    # cube alone, is made beside the dense sums (not beside the larger cubes' tiered chain,
    # whose memory it would add to: 530 instead of 430 MB peak for a 1500 x 750 input), the
    # rest in the write stage below
    pool = ThreadPoolExecutor(max_workers=_WRITE_THREADS)

    def preview(name: str, faces: NDArray[np.float32], exposure: float, layout: str
                ) -> dict[str, Any]:
        path = imageio.write_preview_png(out / f"preview_{name}.png", faces, exposure=exposure,
                                         durable=False)
        fsync_file(path)
        return {"path": path.name, "kind": "preview", "of": name, "level": None,
                "roughness": None, "layout": layout, "format": "png"}

    try:
        previews = []
        if settings.previews:
            exposure = imageio.cube_exposure(cube)  # one for all previews, so they compare
            if dense:
                previews.append(pool.submit(preview, "input", cube, exposure, "hcross"))

        # --- compute everything (the staging folder gets the input's preview meanwhile) --
        t = time.perf_counter()
        bands = settings.sh_bands
        coeffs = sh.project_cube(cube, bands=bands)
        # band 2, what sh.json's consumers and the glTF light take (the same projection at 3 bands)
        sh9 = coeffs if bands == 3 else sh.project_cube(cube)
        irr_min, irr_min_dir = sh.min_over_sphere(sh.irradiance_coefficients(coeffs, bands=bands),
                                                  bands=bands)
        timings["sh"] = time.perf_counter() - t

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
                        workers=1 if n <= 128 else 2)[0]
                return d, None, time.perf_counter() - t
            d, inf = diffuse.diffuse_sh(cube, settings.diffuse_size, window=settings.sh_window,
                                        width=settings.sh_window_width, bands=bands)
            return d, inf, time.perf_counter() - t

        spec_kwargs: dict[str, Any] = {"levels": levels, "method": settings.specular_method}
        if settings.samples is not None:
            spec_kwargs["samples"] = settings.samples
        if dense:
            # one pass of dense sums over every input texel: the diffuse map and every GGX level
            # (exact), the cube's symmetries shared, the blocks split between two threads
            t = time.perf_counter()
            diff, *rest = specular.symmetric_zonal_sums(cube, outs, workers=2, far_field=True)
            spec = [cube.copy(), *rest]
            info = None
            timings["specular"] = time.perf_counter() - t
            timings["diffuse"] = 0.0  # (in the specular figure: one pass computed both)
        else:
            diff, info, spec = _separate_stages(cube, settings, spec_kwargs, diffuse_stage, timings)
        if info is not None:
            sh_window = {
                "window": info.window,
                "width": info.width if np.isfinite(info.width) else None,
                "min_irradiance_over_pi_after_window": [float(x) for x in info.minimum],
                "coefficients_after_window": [[float(x) for x in row] for row in info.coefficients],
            }

        t = time.perf_counter()
        lut = usercache.dfg_lut(settings.lut_size)  # computed once per machine (same bits)
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

        # --- write (into the staging folder) -------------------------------------------
        manifest_path = out / "manifest.json"
        t = time.perf_counter()
        conv = conventions()
        attrs = {"probegrid:conventions": json.dumps(conv), "probegrid:version": __version__}
        files: list[dict[str, Any]] = []
        ext = settings.format
        write_layout = settings.output_layout

        def write_cube(stem: str, faces: NDArray[np.float32], **meta: Any) -> dict[str, Any]:
            written = imageio.write_cube(
                out / stem, faces, layout=write_layout, fmt=ext, half=settings.half,
                metadata={**attrs, "probegrid:kind": meta["kind"]},
                durable=False,  # flushed here, and by staged_output before publishing
                parallel=False,  # (the pool writes several cubes at once)
            )
            for p in written:
                fsync_file(p)
            rel = [str(Path(p).relative_to(out)) for p in written]
            return {
                "path": rel[0] if len(rel) == 1 else rel,
                "layout": write_layout,
                "face_size": int(faces.shape[1]),
                "format": ext,
                "dtype": written.pixel_type,  # half, or float where a value exceeds half
                "seam": settings.seam,
                **meta,
            }

        # (the pool encodes the maps and previews while this thread writes sh.json and the LUT)
        if settings.previews:
            say("writing maps and previews")
            if not previews:
                previews.append(pool.submit(preview, "input", cube, exposure, "hcross"))
            previews += [  # (the largest first)
                pool.submit(preview, "specular", _specular_sheet(spec), exposure,
                            "hcross per level, level 0 at the top"),
                pool.submit(preview, "diffuse", diff, exposure, "hcross"),
            ]
        else:
            say("writing maps")
        maps = []
        if ext not in ("ktx2", "gltf"):
            maps.append(pool.submit(write_cube, "diffuse", diff_out, kind="diffuse", level=0,
                                    roughness=None, content="irradiance / pi",
                                    method=settings.diffuse_method,
                                    sh_window=sh_window["window"]))
            for k, lv in enumerate(spec_out):
                r = float(lobes.level_roughness(k, levels))
                maps.append(pool.submit(write_cube, f"specular_m{k}", lv, kind="specular",
                                        level=k, roughness=r, alpha=r * r))
        elif ext == "ktx2":  # specular.ktx2 (the chain as mips) and diffuse.ktx2
            from probegrid.export.environment import write_environment_ktx2

            files += write_environment_ktx2(out, diff_out, spec_out,
                                            vk_format=97 if settings.half else 109,
                                            cube_convention=settings.cube_convention,
                                            key_values={"probegrid:conventions":
                                                        json.dumps(conv)})
        else:  # environment.gltf (EXT_lights_image_based) and its RGBD PNG faces
            files += gltf_ibl.write_environment_gltf(out, spec_out, sh9)

        band_factors = sh.clamped_cosine_factors(bands)
        sh_doc = {
            "coefficients": [[float(x) for x in row] for row in coeffs],
            "bands": bands,
            "basis": conv["sh_basis"] if bands == 3 else sh.basis_description(bands),
            "constants": dict(list(conv["sh_constants"].items())[:bands * bands]),
            "content": "radiance coefficients L_lm (RGB); irradiance E(n) = sum A_l L_lm "
                       "Y_lm(n), "
                       + ("A = (pi, 2pi/3, pi/4)" if bands == 3 else
                          "A_l = band_factors (A_0 = pi, A_1 = 2pi/3, 0 for odd l > 1, "
                          "Ramamoorthi & Hanrahan 2001 eq. 8 for even l)"),
            "band_factors": [float(a) for a in band_factors],
            "min_irradiance_over_pi": [float(x) / np.pi for x in irr_min],
            "min_irradiance_direction": [[float(x) for x in d] for d in irr_min_dir],
            "diffuse_map": {"method": settings.diffuse_method, **sh_window},
            "consumers": sh_forms(sh9),  # the consumers take band 2 (9 coefficients)
        }
        atomic_write_json(out / "sh.json", sh_doc)

        lut_rgb = np.concatenate([lut, np.zeros(lut.shape[:2] + (1,), np.float32)], axis=-1)
        fsync_file(imageio.write_image(out / "dfg_lut.exr", lut_rgb, half=False,
                                       metadata={**attrs, "probegrid:kind": "lut"},
                                       durable=False))
        lut_entry = {"path": "dfg_lut.exr", "kind": "lut", "level": None, "roughness": None,
                     "layout": "x = N.V (columns), y = perceptual roughness (rows)",
                     "format": "exr", "dtype": "float", "channels": "R = A, G = B, B = 0",
                     "size": settings.lut_size}
        sh_entry = {"path": "sh.json", "kind": "sh", "level": None, "roughness": None,
                    "layout": None, "format": "json"}
        entries = {f["of"]: f for f in (p.result() for p in previews)}
        files += [m.result() for m in maps] + [sh_entry, lut_entry] + [
            entries[name] for name in ("input", "diffuse", "specular") if name in entries]
    finally:  # (on an error too: no task writes into the staging folder after this, which
        # is then removed)
        pool.shutdown(wait=True, cancel_futures=True)
    timings["write"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0

    manifest = {
        "format": FILTER_FORMAT,
        "format_version": 1,
        "probegrid_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "input": {"paths": [str(p) for p in paths], "layout": in_layout,
                  "source_size": list(source_wh),
                  "nonfinite_values_replaced": nonfinite,
                  "negative_values": {"count": negative, "action": (
                      "kept" if settings.keep_negative and settings.clamp is None
                      else "set to 0")},
                  "cube_size": n, "diffuse_source_size": diffuse_source},
        "settings": settings.as_dict(),
        "conventions": conv,
        "specular": {"levels": levels, "sizes": [int(lv.shape[1]) for lv in spec],
                     "method": ("dense sums over every input texel (the far field of lobes "
                                "narrower than alpha 0.06 over 2x2 merged texels)" if dense
                                else settings.specular_method),
                     "roughness": ([float(r) for r in lobes.level_roughness(np.arange(levels),
                                                                           levels)]
                                   if ext != "gltf" else
                                   [float(np.sqrt(a)) for a in gltf_ibl.babylon_alphas(n)])},
        "quality": {
            "sh_min_irradiance_over_pi": [float(x) / np.pi for x in irr_min],
            "diffuse_sh_window": sh_window,
            "energy": energy,
            "seam_score": seam_scores,
        },
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
        "files": files,
    }
    atomic_write_json(manifest_path, manifest)
    return manifest, files


def _separate_stages(cube: NDArray[np.float32], settings: FilterSettings,
                     spec_kwargs: dict[str, Any], diffuse_stage: Callable[[], Any],
                     timings: dict[str, float]) -> tuple[NDArray[np.float32], Any, list[Any]]:
    """The diffuse map and the specular chain by their own functions (every case but the
    default one of :func:`_filter_into`); returns (diffuse, SH window info or None, chain)."""
    from probegrid.core import specular

    n = cube.shape[1]
    # the diffuse sum runs in a second thread beside the GGX chain (both spend their time in
    # numpy calls that release the GIL; the chain limits BLAS to one thread), for cubes up to
    # 128^2: the chain of a larger cube needs the memory (peak RSS 530 vs 480 MB at 256^2)
    with ThreadPoolExecutor(max_workers=1) as pool:
        diffuse_future = pool.submit(diffuse_stage) if n <= 128 else None
        t = time.perf_counter()
        if settings.format != "gltf":
            spec = specular.ggx_prefilter(cube, **spec_kwargs)
        else:
            from probegrid.export import gltf_ibl

            spec = gltf_ibl.specular_chain(cube)  # Babylon's mip -> alpha mapping
        timings["specular"] = time.perf_counter() - t
        if n > 128:  # one cube of this size: its plans are not reused, free them for the rest
            specular.clear_caches()
        diff, info, timings["diffuse"] = (diffuse_future.result() if diffuse_future is not None
                                          else diffuse_stage())
    return diff, info, spec


def _specular_sheet(levels: Sequence[NDArray[np.float32]]) -> NDArray[np.float32]:
    """Every specular level as a horizontal cross, nearest-upsampled to one size, stacked."""
    from probegrid.core import layouts

    n = min(int(levels[0].shape[1]), 64)
    rows = []
    for lv in levels:
        m = int(lv.shape[1])
        if m >= n:
            step = m // n
            faces = lv[:, ::step, ::step][:, :n, :n]
        else:
            rep = n // m
            faces = np.repeat(np.repeat(lv, rep, axis=1), rep, axis=2)
        rows.append(layouts.faces_to_cross(faces, "hcross"))
    return np.concatenate(rows, axis=0)
