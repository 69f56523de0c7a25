"""``probegrid filter``: one HDR environment in; diffuse, specular, SH, DFG LUT and a manifest out.

The job: read the environment files (one image in any layout :mod:`probegrid.core.layouts`
knows, or six face files ordered by their names), filter it with
:func:`probegrid.filter.filter_environment` (the DFG table through the per-machine cache,
:mod:`probegrid.usercache`), then write the maps in the chosen format and layout, ``sh.json``,
the LUT, PNG previews and, last, ``manifest.json``. Option combinations that cannot work and an
output location that cannot be written are refused before any work
(:func:`probegrid.filter.check_settings`, :func:`probegrid.jobs.staging.staged_output`).
Everything is written into a staging folder beside the output directory and moved into place
only when complete, so a failed or interrupted run leaves the output directory as it was (an
earlier output whole) and no temporary file: a directory with a manifest holds a finished job.
The maps and the previews are encoded and flushed to disk by a pool of threads (one per core
by default, ``workers``; a map's six faces by the same one) while the main thread writes
``sh.json`` and the LUT.

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
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from probegrid._fs import atomic_write_json, fsync_file
from probegrid._machine import available_cores
from probegrid._types import ImageFormat
from probegrid._version import __version__
from probegrid.core.color import PREVIEW_TONE_MAPPING
from probegrid.core.conventions import conventions
from probegrid.filter import (
    FilteredEnvironment,
    FilterSettings,
    Progress,
    check_settings,
    default_cube_size,
)

__all__ = ["FILTER_FORMAT", "FilterResult", "prepare_output_dir", "run_filter"]

#: ``format`` of the manifest of a filter output directory.
FILTER_FORMAT = "probegrid.filter"


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
        low = min(q["sh_min_irradiance_over_pi"])
        if low < 0:  # as the bake says of its raw SH
            lines.append(
                f"  warning:   the SH's irradiance is negative in some directions (min "
                f"irradiance/pi {low:.4g}): ringing of the truncated projection; a consumer "
                "that clamps it (three.js) shows black there. Window the coefficients "
                "(probegrid.core.sh.dering) or light with the diffuse map")
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


def run_filter(
    env: Sequence[str | os.PathLike[str]] | str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    settings: FilterSettings | None = None,
    *,
    progress: Progress | None = None,
    workers: int | None = None,
    max_pixels: int | None = None,
) -> FilterResult:
    """Run the whole filter job; see the module docstring. Returns what was written.

    ``workers`` threads filter and write (default: the process's cores,
    :func:`probegrid._machine.available_cores`); the files do not depend on it.
    ``max_pixels`` (default :data:`probegrid.imageio.MAX_PIXELS`, 2^28) bounds an input
    image's pixels, checked from the headers before any work (``--max-pixels``); an input more
    than twice as fine as the cube needs is read reduced, a band of rows at a time, so memory
    follows the output's size (:func:`probegrid.imageio.reduced_environment_shape`).

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
    if len(paths) == 1 and settings.layout == "auto":  # from the header, before any pixel
        from probegrid.imageio import detect_file_layout

        detect_file_layout(paths[0], option="--layout")
    from probegrid.imageio import check_pixels

    check_pixels(paths, max_pixels=max_pixels, option="--max-pixels")  # (before any work)
    with staged_output(out, lambda final: prepare_output_dir(final, FILTER_FORMAT,
                                                             create=False)) as stage:
        manifest, files = _filter_into(stage, paths, settings, progress,
                                       available_cores() if workers is None else workers,
                                       max_pixels)
    return FilterResult(out, manifest, files)


def _environment_files(paths: Sequence[Path], settings: FilterSettings) -> list[Path]:
    """The environment's files: one image, or six face files ordered by their names (not the
    shell's sort); a ``ValueError`` for any other count or for one file with layout faces."""
    from probegrid import imageio

    if len(paths) == 6 and settings.layout in ("auto", "faces"):
        return imageio.order_face_files(paths)
    if len(paths) == 1:
        if settings.layout == "faces":
            raise ValueError("layout 'faces' needs six face files (+X, -X, +Y, -Y, +Z, -Z)")
        return list(paths)
    raise ValueError(f"give one environment image or six face files, got {len(paths)} files")


def _read_environment(files: Sequence[Path], settings: FilterSettings, *,
                      max_pixels: int | None = None, say: Progress | None = None
                      ) -> NDArray[np.float32]:
    """The pixels of one image, or of six square face files of one size as ``(6, n, n, C)``;
    an input more than twice as fine as the cube needs is read reduced to that
    (:func:`probegrid.imageio.reduced_environment_shape`), a band of rows at a time."""
    from probegrid import imageio
    from probegrid.core.layouts import detect_layout

    def need(path: Path, layout: str) -> tuple[tuple[int, int] | None, str]:
        w, h = imageio.image_size(path)
        if layout == "auto":
            try:
                layout = detect_layout(h, w)
            except ValueError:
                return None, layout  # (the pipeline says why)
        n = settings.size or default_cube_size(h, w, layout)
        shape = imageio.reduced_environment_shape(h, w, layout, n)  # type: ignore[arg-type]
        if shape is not None and say is not None:
            say(f"reading {path.name} ({w}x{h}) area-averaged to {shape[1]}x{shape[0]}, "
                f"twice what a {n}^2 cube needs")
        return shape, layout

    def read(path: Path, shape: tuple[int, int] | None, layout: str) -> NDArray[np.float32]:
        return imageio.read_image(path, max_pixels=max_pixels, shape=shape,
                                  option="--max-pixels", equirect=layout == "equirect")

    if len(files) == 1:
        return read(files[0], *need(files[0], settings.layout))
    sizes = {imageio.image_size(p) for p in files}
    shape = need(files[0], "faces")[0] if len(sizes) == 1 else None
    images = [read(p, shape, "faces") for p in files]
    if len({im.shape for im in images}) != 1 or images[0].shape[0] != images[0].shape[1]:
        raise ValueError(
            "six face files must be square images of one size, got "
            + ", ".join(f"{im.shape[1]}x{im.shape[0]}" for im in images)
        )
    return np.stack(images)


def _filter_into(
    out: Path, paths: Sequence[str | os.PathLike[str]], settings: FilterSettings,
    progress: Progress | None, workers: int, max_pixels: int | None = None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Read the environment, filter it, then write everything into the (staging) directory
    ``out``; returns the manifest and its file list."""
    from probegrid import usercache
    from probegrid.filter import filter_environment

    from probegrid.imageio import image_size as imageio_size

    say: Progress = progress or (lambda _m: None)
    t0 = time.perf_counter()
    files = _environment_files([Path(p) for p in paths], settings)
    file_size = imageio_size(files[0])  # (the source_size is what was read: maybe reduced)
    read = [0.0]

    def source() -> NDArray[np.float32]:
        pixels = _read_environment(files, settings, max_pixels=max_pixels, say=say)
        read[0] = time.perf_counter() - t0
        return pixels

    # (the image handed on, not kept here: the filter frees it once resampled)
    env = filter_environment(source(), settings=settings, progress=say, workers=workers,
                             dfg_lut=usercache.dfg_lut, name=str(files[0]))
    timings = {**env.timings, "read": read[0] + env.timings["read"]}

    t = time.perf_counter()
    manifest_path = out / "manifest.json"
    conv = conventions()
    # every map file and preview is encoded in one pool of threads (the encoders, the tone
    # mapping and the flushes release the GIL), each task flushing its files to disk (the
    # staging folder's commit then finds them there), while this thread writes sh.json and
    # the LUT
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        if settings.previews:
            say("writing maps and previews")
            previews = _submit_previews(pool, out, env)
        else:
            say("writing maps")
            previews = []
        files, maps = _write_maps(pool, out, env, settings, conv)
        sh_entry = _write_sh(out / "sh.json", env, settings, conv)
        lut_entry = _write_lut(out / "dfg_lut.exr", env.dfg_lut, settings.lut_size, conv)
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
        "input": {"paths": [str(p) for p in paths], "layout": env.layout,
                  "source_size": list(env.source_size),
                  "file_size": list(file_size),
                  "nonfinite_values_replaced": env.nonfinite,
                  "negative_values": {"count": env.negative, "action": env.negative_action},
                  "cube_size": env.cube_size, "diffuse_source_size": env.diffuse_source_size},
        "settings": settings.as_dict(),
        "conventions": conv,
        "specular": {"levels": env.levels, "sizes": [int(lv.shape[1]) for lv in env.specular],
                     "method": env.specular_method, "roughness": env.roughness},
        "quality": {
            "sh_min_irradiance_over_pi": [float(x) / np.pi for x in env.sh_min_irradiance],
            "diffuse_sh_window": env.sh_window,
            "energy": env.energy,
            "seam_score": env.seam_score,
        },
        "previews": ({"tone_mapping": PREVIEW_TONE_MAPPING} if settings.previews else None),
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
        "files": files,
    }
    atomic_write_json(manifest_path, manifest)
    return manifest, files


def _attributes(conv: dict[str, Any], kind: str) -> dict[str, str]:
    """The metadata every written EXR/HDR file carries."""
    return {"probegrid:conventions": json.dumps(conv), "probegrid:version": __version__,
            "probegrid:kind": kind}


def _submit_previews(pool: ThreadPoolExecutor, out: Path, env: FilteredEnvironment
                     ) -> list[Future[dict[str, Any]]]:
    """The PNG previews of the input, the specular chain and the diffuse map, each tone-mapped
    by its own statistics (:data:`probegrid.imageio.PREVIEW_TONE_MAPPING`: a preview whose
    exposure came from the input would show a bright studio's diffuse map a third white),
    encoded by ``pool``; their manifest entries."""
    from probegrid import imageio

    def preview(name: str, faces: NDArray[np.float32], layout: str) -> dict[str, Any]:
        path = imageio.write_preview_png(out / f"preview_{name}.png", faces, durable=False)
        fsync_file(path)
        return {"path": path.name, "kind": "preview", "of": name, "level": None,
                "roughness": None, "layout": layout, "format": "png",
                "tone_mapping": PREVIEW_TONE_MAPPING}

    return [
        pool.submit(preview, "input", env.cube, "hcross"),
        pool.submit(preview, "specular", _specular_sheet(env.specular),  # (the largest first)
                    "hcross per level, level 0 at the top"),
        pool.submit(preview, "diffuse", env.diffuse, "hcross"),
    ]


def _write_maps(pool: ThreadPoolExecutor, out: Path, env: FilteredEnvironment,
                settings: FilterSettings, conv: dict[str, Any]
                ) -> tuple[list[dict[str, Any]], list[Future[dict[str, Any]]]]:
    """The diffuse map and the specular chain (seam mode applied) in ``settings.format``: one
    image set per map encoded by ``pool`` (EXR, HDR), or the KTX2 pair or the glTF file
    written here; returns the entries written and the pending ones."""
    from probegrid import imageio

    ext, layout = settings.format, settings.output_layout
    fmt = cast(ImageFormat, ext)  # (ktx2, gltf and filament are written below, not by write_cube)

    def write_cube(stem: str, faces: NDArray[np.float32], **meta: Any) -> dict[str, Any]:
        written = imageio.write_cube(
            out / stem, faces, layout=layout, fmt=fmt, half=settings.half,
            metadata=_attributes(conv, meta["kind"]),
            durable=False,  # flushed here, and by staged_output before publishing
            parallel=False,  # (the pool writes several cubes at once)
        )
        for p in written:
            fsync_file(p)
        rel = [str(Path(p).relative_to(out)) for p in written]
        return {
            "path": rel[0] if len(rel) == 1 else rel,
            "layout": layout,
            "face_size": int(faces.shape[1]),
            "format": ext,
            "dtype": written.pixel_type,  # half, or float where a value exceeds half
            "seam": settings.seam,
            **meta,
        }

    if ext == "ktx2":  # specular.ktx2 (the chain as mips) and diffuse.ktx2
        from probegrid.export.environment import write_environment_ktx2

        vk_format = settings.vk_format or ("R16G16B16A16_SFLOAT" if settings.half
                                           else "R32G32B32A32_SFLOAT")
        return write_environment_ktx2(out, env.diffuse_export, env.specular_export,
                                      vk_format=vk_format, zstd=settings.zstd,
                                      cube_convention=settings.cube_convention,
                                      key_values={"probegrid:conventions": json.dumps(conv)}), []
    if ext == "gltf":  # environment.gltf (EXT_lights_image_based) and its RGBD PNG faces
        from probegrid.export import gltf_ibl

        return gltf_ibl.write_environment_gltf(out, env.specular_export, env.sh9), []
    if ext == "filament":  # environment_ibl.ktx (chain + SH) and environment_skybox.ktx (KTX1)
        from probegrid.export import filament

        return filament.write_filament_ibl(out, env.specular_export, env.sh9), []
    maps = [pool.submit(write_cube, "diffuse", env.diffuse_export, kind="diffuse", level=0,
                        roughness=None, content="irradiance / pi",
                        method=settings.diffuse_method, sh_window=env.sh_window["window"])]
    for k, lv in enumerate(env.specular_export):
        r = env.roughness[k]
        maps.append(pool.submit(write_cube, f"specular_m{k}", lv, kind="specular", level=k,
                                roughness=r, alpha=r * r))
    return [], maps


def _write_sh(path: Path, env: FilteredEnvironment, settings: FilterSettings,
              conv: dict[str, Any]) -> dict[str, Any]:
    """``sh.json``: the radiance coefficients, their basis and constants, the irradiance they
    imply, the diffuse map's SH window and the consumers' forms of band 2; its manifest entry."""
    from probegrid.core import sh
    from probegrid.export.shforms import sh_forms

    bands = settings.sh_bands
    band_factors = sh.clamped_cosine_factors(bands)
    sh_doc = {
        "coefficients": [[float(x) for x in row] for row in env.sh],
        "bands": bands,
        "basis": conv["sh_basis"] if bands == 3 else sh.basis_description(bands),
        "constants": dict(list(conv["sh_constants"].items())[:bands * bands]),
        "content": "radiance coefficients L_lm (RGB); irradiance E(n) = sum A_l L_lm "
                   "Y_lm(n), "
                   + ("A = (pi, 2pi/3, pi/4)" if bands == 3 else
                      "A_l = band_factors (A_0 = pi, A_1 = 2pi/3, 0 for odd l > 1, "
                      "Ramamoorthi & Hanrahan 2001 eq. 8 for even l)"),
        "band_factors": [float(a) for a in band_factors],
        "min_irradiance_over_pi": [float(x) / np.pi for x in env.sh_min_irradiance],
        "min_irradiance_direction": [[float(x) for x in d]
                                     for d in env.sh_min_irradiance_direction],
        "diffuse_map": {"method": settings.diffuse_method, **env.sh_window},
        "consumers": sh_forms(env.sh9),  # the consumers take band 2 (9 coefficients)
    }
    atomic_write_json(path, sh_doc)
    return {"path": path.name, "kind": "sh", "level": None, "roughness": None,
            "layout": None, "format": "json"}


def _write_lut(path: Path, lut: NDArray[np.float32], size: int, conv: dict[str, Any]
               ) -> dict[str, Any]:
    """The DFG table as a float EXR (``B = 0``); its manifest entry."""
    from probegrid import imageio

    lut_rgb = np.concatenate([lut, np.zeros(lut.shape[:2] + (1,), np.float32)], axis=-1)
    fsync_file(imageio.write_image(path, lut_rgb, half=False,
                                   metadata=_attributes(conv, "lut"), durable=False))
    return {"path": path.name, "kind": "lut", "level": None, "roughness": None,
            "layout": "x = N.V (columns), y = perceptual roughness (rows)",
            "format": "exr", "dtype": "float", "channels": "R = A, G = B, B = 0",
            "size": size}


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
