"""The ``probegrid`` command line.

Sub-commands parse their options into the settings objects of the library and call it; no
numerical work happens here. Every failure the user can cause (a bad file, a bad option value, a
non-finite pixel) ends with one line ``probegrid: error: ...`` on stderr and a non-zero exit code
(2 for bad input, 130 for an interrupt); ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import re
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal, NoReturn, get_args, get_origin

from probegrid._types import (
    CubeConvention,
    CubeLayout,
    EngineTarget,
    ImageFormat,
    SHKind,
    choices,
)

__all__ = ["build_parser", "main"]

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_INTERNAL = 1
#: Exit code when stdout's reader went away (as a process killed by SIGPIPE).
EXIT_BROKEN_PIPE = 141


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def _positive_int(text: str) -> int:
    v = _int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _positive_seconds(text: str) -> float:
    v = _finite_float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return v


def _finite_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _rgb(text: str) -> str:
    """``R,G,B`` (or one value for grey) of finite, non-negative numbers; the text itself."""
    try:
        rgb = [float(x) for x in text.split(",")]
    except ValueError:
        rgb = []
    if len(rgb) not in (1, 3) or not all(math.isfinite(v) and v >= 0 for v in rgb):
        raise argparse.ArgumentTypeError(
            f"expected R,G,B (or one value) of finite numbers >= 0, got {text!r}")
    return text


@functools.cache
def _fields(model: type) -> dict[str, tuple[Any, Any]]:
    """Each field of a settings class, a pydantic model or a dataclass: (default, type); read
    once per class (resolving a dataclass's annotations takes 0.3 ms)."""
    if hasattr(model, "model_fields"):  # a pydantic model
        return {k: (f.default, f.annotation) for k, f in model.model_fields.items()}
    import dataclasses
    from typing import get_type_hints

    hints = get_type_hints(model)
    return {f.name: (f.default, hints[f.name]) for f in dataclasses.fields(model)}


def _option(p: argparse.ArgumentParser, model: type, field: str, *flags: str,
            help: str, **kwargs: Any) -> None:
    """An option that fills ``model``'s ``field``: its type, choices and default come from the
    model (the one place they are written). Options not given stay out of the namespace
    (``argparse.SUPPRESS``), so the model's default applies and the model validates every value.

    A boolean field defaulting to true is switched off by its flag (``--no-direct``), one
    defaulting to false switched on (``--store-incoming``).
    """
    default, ann = _fields(model)[field]
    kinds = [ann] if get_origin(ann) is Literal else [
        a for a in (get_args(ann) or (ann,)) if a is not type(None)]
    flags = flags or (f"--{field.replace('_', '-')}",)
    kw: dict[str, Any] = {"dest": field, "default": argparse.SUPPRESS}
    if ann is bool:
        kw["action"] = "store_false" if default else "store_true"
    else:
        literal = next((a for a in kinds if get_origin(a) is Literal), None)
        if literal is not None and int in kinds:  # an int or a word (--bounces 2 / converge)
            words = get_args(literal)
            def int_or_word(text: str, words: tuple[str, ...] = words) -> int | str:
                if text in words:
                    return text
                try:
                    return int(text)
                except ValueError:
                    raise argparse.ArgumentTypeError(
                        f"expected an integer or {' or '.join(words)}, got {text!r}") from None

            kw["type"] = int_or_word
            kw["metavar"] = "{N," + ",".join(words) + "}"
        elif literal is not None:
            kw["choices"] = get_args(literal)
        elif int in kinds:
            kw["type"] = _int
        elif float in kinds:
            kw["type"] = _finite_float
        if default is not None:
            help = f"{help} (default: {default})"
    kw.update(kwargs)
    p.add_argument(*flags, help=help, **kw)


def _given(args: argparse.Namespace, model: type) -> dict[str, Any]:
    """The options of ``args`` that fill fields of ``model`` (those given on the command line)."""
    names = _fields(model)
    return {k: v for k, v in vars(args).items() if k in names}


def _add_filter(sub: argparse._SubParsersAction) -> None:
    from probegrid.filter import FilterSettings
    from probegrid.imageio import FACE_ORDER_HELP

    p = sub.add_parser(
        "filter",
        help="filter an HDR environment into diffuse and specular maps",
        description=(
            "Read one HDR environment (or six face files) and write its diffuse map "
            "(irradiance/pi), GGX specular mip chain, SH coefficients, the DFG LUT, PNG previews "
            "and manifest.json into --out."
        ),
    )
    p.add_argument("env", nargs="+", type=Path,
                   help=f"environment image, or six face files ({FACE_ORDER_HELP})")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    F = FilterSettings
    _option(p, F, "layout", help="input layout (auto: detected from the aspect ratio)")
    _option(p, F, "size", help="cube face size of the specular level 0 (default: from the input)")
    _option(p, F, "diffuse_size", help="diffuse face size")
    _option(p, F, "diffuse_method",
            help="exact clamped-cosine integral, or via SH coefficients (--sh-bands)")
    _option(p, F, "diffuse_source_size",
            help="face size the exact diffuse sum reads (the cube's box mip; default: the cube up "
                 "to 128, the 128 mip of larger cubes)")
    _option(p, F, "specular_levels", help="mip levels (default: the full chain)")
    _option(p, F, "specular_method",
            help="GGX prefilter: tiered exact-kernel convolution, filtered importance sampling, "
                 "or the brute-force exact convolution (slow)")
    _option(p, F, "samples", help="samples per texel for --specular-method fis")
    _option(p, F, "sh_bands",
            help="SH bands for sh.json and --diffuse-method sh (3 = 9 coefficients; up to 16)")
    _option(p, F, "sh_window",
            help="SH windowing against ringing (auto: the least that makes irradiance >= 0)")
    _option(p, F, "sh_window_width", help="window width (bands)")
    _option(p, F, "format", help="map file format (ktx2: specular.ktx2 with the chain as mips and "
            "diffuse.ktx2, RGBA16F, or RGBA32F with --float; gltf: environment.gltf with "
            "EXT_lights_image_based, RGBD PNG faces down to 16^2, as Babylon.js reads it; "
            "filament: environment_ibl.ktx and environment_skybox.ktx, KTX1 R11F_G11F_B10F "
            "with the SH in key 'sh', as cmgen writes them for Filament)")
    _option(p, F, "cube_convention",
            help="ktx2 cube faces for that consumer's lookup: the OpenGL/KTX2 table (glTF "
                 "Sample Viewer), mirrored in x (three.js) or z (Bevy)")
    _option(p, F, "vk_format", help="--format ktx2 texel format (default: "
            "R16G16B16A16_SFLOAT, R32G32B32A32_SFLOAT with --float; E5B9G9R9_UFLOAT_PACK32: "
            "4 bytes a texel, no negative values), as export --target ktx2 takes it")
    _option(p, F, "zstd", help="Zstandard-supercompressed KTX2 (--format ktx2)")
    _option(p, F, "half", "--float", help="write float32 EXR (or KTX2) instead of half")
    _option(p, F, "output_layout", help="layout of the written maps")
    _option(p, F, "seam", help="seam export mode for consumers without seamless cube filtering")
    _option(p, F, "clamp",
            help="clamp radiance to [0, CLAMP]; NaN becomes 0 (otherwise non-finite pixels are "
                 "an error)")
    _option(p, F, "keep_negative",
            help="keep negative input pixels (by default they are set to 0 and counted)")
    _option(p, F, "lut_size", help="DFG LUT size")
    _option(p, F, "previews", "--no-previews", help="skip the PNG previews")
    p.add_argument("--max-pixels", type=_positive_int, metavar="N",
                   help="most pixels an input image may have, checked from its header "
                        "(default: 2^28 = 268 M); a larger input than the cube needs is read "
                        "reduced, in bands, whatever its size")
    p.set_defaults(handler=_run_filter)


def _run_filter(args: argparse.Namespace) -> int:
    from probegrid.filter import FilterSettings
    from probegrid.jobs.filter import run_filter

    settings = FilterSettings(**_given(args, FilterSettings))
    result = run_filter(args.env, args.out, settings, progress=_stderr_progress,
                        max_pixels=args.max_pixels)
    print(result.summary())
    return 0


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job on the bundled sample data",
        description=(
            "Filter the bundled sample sky, bake the bundled sample room into a probe grid "
            "store (unless it exists), print what was made, then serve the store."
        ),
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"),
                   help="output directory (default: out/demo)")
    p.add_argument("--no-serve", action="store_true", help="stop after filtering and baking")
    p.add_argument("--port", type=int, default=8000,
                   help="TCP port the store is served on, at 127.0.0.1 (default: 8000)")
    p.set_defaults(handler=_run_demo)


def _run_demo(args: argparse.Namespace) -> int:
    from probegrid.bake.executors.local import stop_fork_server
    from probegrid.jobs.demo import run_demo

    print(run_demo(args.out, progress=_stderr_progress), flush=True)
    stop_fork_server()  # the bake's fork server is not needed to serve
    if not args.no_serve:
        print("\nServing the store (Ctrl-C stops):")
        _serve([args.out / "sample_room.probes"], "127.0.0.1", args.port, 1)
    return 0


def _add_bake(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bake",
        help="bake a probe grid of a glTF scene into a store",
        description=(
            "Ray-trace the incoming light at every point of a 3D grid of SCENE (glTF 2.0), "
            "iterate bounces, convolve each probe into SH, a diffuse cube and a GGX specular "
            "chain, and write a memory-mappable store NAME.probes. An interrupted bake resumes "
            "when the same command is run again."
        ),
    )
    p.add_argument("scene", type=Path, help="glTF 2.0 scene (.gltf or .glb)")
    p.add_argument("--out", required=True, type=Path, help="store directory NAME.probes")
    from probegrid.bake import BakeSettings  # (imported by the bake command only: heavy)
    from probegrid.imageio import FACE_ORDER_HELP
    from probegrid.jobs.bake import BakeJob

    J, S = BakeJob, BakeSettings
    g = p.add_mutually_exclusive_group()
    _option(g, J, "grid", help="probe counts NXxNYxNZ (default: a spacing of the longest "
            "side / 8, fitted to the scene's free space)")
    _option(g, J, "spacing",
            help="probes exactly S (or SX,SY,SZ) apart, centred in the box (scene units)")
    _option(p, J, "bounds", help="grid box x0,y0,z0,x1,y1,z1 (default: the scene bounds, "
            "probes at the centres of the grid's cells)")
    _option(p, J, "volume_node", metavar="NAME",
            help="grid box from the glTF node NAME: the unit cube -0.5..0.5 by the node's world "
            "transform, as Bevy's light probes (a rotated node: the box's axis-aligned bounds); "
            "probes at the centres of its cells. Default: the one node named like a probe "
            "volume (IrradianceVolume, LightProbe, ProbeVolume), if any")
    _option(p, J, "margin", help="grow (or, negative, shrink) the scene bounds (or the volume "
            "node's box) by this much")
    e = p.add_mutually_exclusive_group()
    _option(e, J, "environment", type=Path, nargs=1, metavar="FILE",
            help="HDR environment image (any layout; see --environment-layout)")
    e.add_argument("--environment-faces", dest="environment", type=Path, nargs=6,
                   metavar="FACE", default=argparse.SUPPRESS,
                   help=f"HDR environment as six face files ({FACE_ORDER_HELP})")
    _option(p, J, "environment_layout", help="layout of --environment")
    _option(p, J, "environment_color", type=_rgb, help="constant environment radiance R,G,B")
    _option(p, J, "environment_intensity", help="environment scale")
    _option(p, J, "environment_rotation", help="degrees about +Y (right-handed)")
    _option(p, S, "face_size", help="incoming cube face size")
    _option(p, S, "bounces", help="indirect bounces, or converge: until the estimated limit of "
            "the grid's energy changes by less than --tolerance, then extrapolated to it")
    _option(p, S, "tolerance", help="relative change of the estimated limit that ends "
            "--bounces converge")
    _option(p, S, "max_bounces", help="most bounces --bounces converge makes")
    _option(p, S, "light_samples", help="shadow rays toward the emitters and toward the "
            "environment at every hit (each)")
    _option(p, S, "gather_samples", help="cosine-weighted rays from every hit that bring back "
            "the light bounced off what they hit (0: read the probes at the hit itself)")
    _option(p, S, "gather_depth", help="gather levels before the probes are read: 2 casts one "
            "more ray from every gather ray's hit, 3 one more again (the sample room against a "
            "path tracer: 0.77 %% mean error instead of 0.99 %%, for 1.4x the converged bake's "
            "time)")
    _option(p, S, "samples", help="rays per texel")
    _option(p, S, "seed", help="random seed of the ray jitter")
    _option(p, S, "diffuse_size", help="diffuse cube face size")
    _option(p, S, "specular_levels", help="specular mip levels (default: the full chain)")
    _option(p, S, "direct", "--no-direct",
            help="leave the punctual lights' direct light out of the probes")
    _option(p, S, "store_incoming", help="also store the raw cubes")
    _option(p, S, "relocate", "--no-relocate", help="do not move probes that are inside geometry")
    _option(p, S, "batch_size", help="probes per task")
    _option(p, S, "sh_field", help="lattice steps per probe cell of the SH field /sh "
            "interpolates: radiance SH traced on a lattice finer than the probes' whose outer "
            "layers sit just inside the walls (0: none, /sh blends the probes)")
    _option(p, S, "sh_field_face_size", help="face size the SH field's points are traced at")
    _option(p, S, "final_gather", help="rays per texel of a final view of each probe whose hits "
            "read the surface light cache (built first, finer, and iterated on itself) instead "
            "of gathering: 16 takes the sunlit hall's error against a path tracer from 6.3 %% "
            "to 1.1 %% (diffuse) for 1.1-1.3x the bake's time; 0: none")
    _option(p, S, "surface_cache_spacing", metavar="H",
            help="lattice spacing of the surface light cache traced answers read (scene "
            "units; 0: no cache). Default: from the scene's surface, the finest spacing with at "
            "most one vertex a triangle side plus 8 per texel of a face (8192 at faces 32), "
            "whatever the grid; at most 2^21 vertices (48 MB)")
    _option(p, S, "dtype", help="map arrays (diffuse, specular, incoming) as float32, or as "
            "half floats: half the size, 11 significant bits, values above 65504 (a direct "
            "sun) clamped; the bake prints both sizes")
    x = p.add_mutually_exclusive_group()
    _option(x, J, "workers", help="local worker processes (default: all cores)")
    _option(x, J, "scheduler", help="Dask scheduler address, e.g. tcp://HOST:8786")
    _option(p, J, "overwrite", help="replace an existing store")
    _option(p, J, "allow_black", help="bake a scene without light, or keep a black result")
    _option(p, J, "allow_paths", "--allow-path", type=Path, action="append", metavar="DIR",
            help="a folder besides the scene's own whose files the glTF may name (e.g. "
            "../textures); repeat for more")
    _option(p, J, "ignore_extensions", "--ignore-extension", action="append", metavar="NAME",
            help="bake a glTF that requires this extension with the extension ignored (the "
            "bake names it among what it does not honour); repeat for more, * for all")
    _option(p, J, "max_texture_pixels", metavar="N",
            help="most pixels a texture image may have (refused from its header before any "
            "decoding; 2^27 = 134 M by default)")
    _option(p, J, "max_texture_size", metavar="N",
            help="longest side of a texture as the bake samples it: a larger texture is "
            "area-averaged down on load, its mean colour kept (default: 1024)")
    _option(p, J, "max_environment_pixels", metavar="N",
            help="most pixels an environment image may have, checked from its header before "
            "any work (default: 2^28 = 268 M; a larger one than the cube needs is read "
            "reduced, in bands), as filter's --max-pixels")
    _option(p, J, "progress", "--no-progress", help="no progress bar")
    p.set_defaults(handler=_run_bake)


def _run_bake(args: argparse.Namespace) -> int:
    from probegrid.bake import BakeSettings
    from probegrid.jobs.bake import BakeJob, run_bake
    from probegrid.jobs.staging import check_writable_location

    settings = BakeSettings(**_given(args, BakeSettings))
    given = _given(args, BakeJob)
    check_writable_location(args.out, "store")  # before the scene loads and workers start
    if len(given.get("environment") or ()) == 6:  # face names checked before any work
        from probegrid.imageio import order_face_files

        given["environment"] = order_face_files(given["environment"])
    opts = BakeJob(settings=settings, **given)
    report = run_bake(opts)
    print(report.summary())
    print(f"look at it: probegrid info {args.out}   |   probegrid export {args.out} "
          f"--probe 0,0,0 --out {args.out.with_suffix('')}-probe")
    return 0


def _add_info(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info", help="print a store's manifest in words",
        description=("Print what a probe grid store holds: its grid (counts, box, spacing, how "
                     "a probe's index and position follow from (i, j, k)), the valid probes, "
                     "every array with its type, shape, size and meaning, the bake's settings "
                     "and inputs, the specular levels' roughness, the conventions (world frame, "
                     "cube faces, SH basis, units) and the bake's quality figures. An "
                     "unfinished bake is named as such."))
    p.add_argument("store", type=Path, help="the store directory (NAME.probes)")
    p.set_defaults(handler=_run_info)


def _run_info(args: argparse.Namespace) -> int:
    from probegrid.jobs.export import describe_store

    print(describe_store(args.store))
    return 0


def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export", help="write one probe's maps as image files, or the grid for an engine "
                       "(--target)",
        description=("Write probes of a store as files other tools read: with --probe, each "
                     "probe's diffuse map (irradiance / pi), GGX specular levels "
                     "(specular_m<k>, roughness k / (levels - 1)), incoming light when stored, "
                     "sh.json and PNG previews, named as 'probegrid filter' names them; with "
                     "--target, the whole grid as an engine loads it. manifest.json lists the "
                     "files with their conventions. Probe (i, j, k) is at index (i ny + j) nz "
                     "+ k; 'probegrid info' shows the grid."))
    p.add_argument("store", type=Path, help="the store directory (NAME.probes)")
    p.add_argument("--probe", help="I,J,K (one probe, 0-based lattice indices); or 'all', or a "
                   "box I0,J0,K0:I1,J1,K1 (corners included): a folder I_J_K per probe")
    p.add_argument("--target", choices=choices(EngineTarget),
                   help="the whole grid as an engine loads it (three.js LightProbeGrid atlas, "
                        "Bevy IrradianceVolume, KTX2 cube-map arrays), or with --probe one "
                        "probe as Filament's KTX1 IBL and skybox (filament: needs a store "
                        "baked with --store-incoming); see manifest.json")
    p.add_argument("--vk-format", help="KTX2 format: R16G16B16A16_SFLOAT, R32G32B32A32_SFLOAT "
                   "or E5B9G9R9_UFLOAT_PACK32 (default: the target's)")
    p.add_argument("--zstd", action="store_true", help="Zstandard-supercompressed KTX2")
    p.add_argument("--cube-convention", choices=choices(CubeConvention), default="gltf",
                   help="--target ktx2 cube faces for that consumer's lookup (default: the "
                        "OpenGL/KTX2 table, as glTF-IBL-Sampler writes)")
    p.add_argument("--out", required=True, type=Path,
                   help="output directory (new, or an earlier export of the same kind)")
    p.add_argument("--layout", choices=choices(CubeLayout), default="faces",
                   help="image layout of each cube map: six face files (_px, _nx, _py, _ny, "
                        "_pz, _nz), one horizontal or vertical cross, or a lat-long "
                        "(default: faces)")
    p.add_argument("--format", choices=choices(ImageFormat), default="exr",
                   help="image file format: OpenEXR (float) or Radiance HDR (RGBE) "
                        "(default: exr)")
    p.add_argument("--half", action="store_true",
                   help="half-float EXR (16 bits: half the size, 11 significant bits) instead "
                        "of 32-bit float")
    p.add_argument("--no-previews", dest="previews", action="store_false",
                   help="no PNG previews (written beside each probe's maps otherwise)")
    p.add_argument("--sh", choices=choices(SHKind), default="deringed",
                   help="which SH sh.json and the three.js atlas carry: deringed (each probe "
                        "windowed so that its irradiance is >= 0 everywhere, as /sh answers) "
                        "or raw (the stored projection, may ring negative) (default: deringed)")
    p.set_defaults(handler=_run_export)


def _run_export(args: argparse.Namespace) -> int:
    from probegrid.jobs.export import export_probe

    if args.target is not None:
        from probegrid.jobs.engine_export import export_grid

        if args.layout != "faces" or args.format != "exr" or args.half:
            raise ValueError("--layout, --format and --half apply to image exports (--probe "
                             "without --target); --target writes the engine's own files "
                             "(KTX2, or KTX1 for filament)")

        written = export_grid(args.store, args.out, target=args.target,
                              vk_format=args.vk_format, zstd=args.zstd, probe=args.probe,
                              cube_convention=args.cube_convention, sh=args.sh)
        print(f"wrote {len(written)} files for {args.target} to {args.out}/ (manifest.json "
              "states the consumer and conventions)")
        return 0
    if args.probe is None:
        raise ValueError("export needs --probe I,J,K (one probe's maps) or --target "
                         "threejs|bevy|ktx2 (the grid) or filament (with --probe)")
    if args.vk_format is not None or args.zstd or args.cube_convention != "gltf":
        raise ValueError("--vk-format, --zstd and --cube-convention apply to --target exports")
    if args.probe.strip() == "all" or ":" in args.probe:
        from probegrid.jobs.export import export_probes

        print(export_probes(args.store, args.probe, args.out, layout=args.layout,
                            fmt=args.format, half=args.half, previews=args.previews,
                            sh=args.sh).summary())
        return 0
    written = export_probe(args.store, args.probe, args.out, layout=args.layout,
                           fmt=args.format, half=args.half, previews=args.previews, sh=args.sh)
    print(f"wrote {len(written)} files to {args.out}/ (manifest.json lists them with the "
          "conventions)")
    if written.valid is False:
        print(f"note: probe {','.join(map(str, written.probe))} is invalid (the bake found it "
              "inside geometry); its maps show the inside of a surface, not the room",
              file=sys.stderr)
    return 0


def _add_serve(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="serve probe grid stores over HTTP",
        description=(
            "Serve one or more stores (NAME.probes, served as NAME) with uvicorn. Limits come "
            "from PROBEGRID_* environment variables (see service/settings.py). OpenAPI docs at "
            "/docs."
        ),
    )
    p.add_argument("stores", nargs="+", type=Path, metavar="STORE",
                   help="store directories (NAME.probes), each served as /v1/grids/NAME")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on: 127.0.0.1 this machine only, 0.0.0.0 every "
                        "interface (default: 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default: 8000)")
    p.add_argument("--workers", type=_positive_int, default=1,
                   help="uvicorn worker processes, each with its own memory maps of the "
                        "stores (default: 1)")
    p.add_argument("--request-budget", type=_positive_seconds, metavar="SECONDS",
                   help="most CPU seconds one light-map or shade request may cost, estimated "
                        "from the request before any work; over it: 422 over_budget "
                        "(default: 2, or PROBEGRID_REQUEST_BUDGET)")
    p.add_argument("--header-timeout", type=_positive_seconds, metavar="SECONDS",
                   help="seconds a client has to send a request's line and headers; then 408 "
                        "and the connection closed (default: 10)")
    p.add_argument("--body-timeout", type=_positive_seconds, metavar="SECONDS",
                   help="seconds a client has to send a request's body after its headers "
                        "(default: 30)")
    p.set_defaults(handler=_run_serve)


def _serve(stores: Sequence[Path], host: str, port: int, workers: int,
           limits: dict[str, float] | None = None) -> None:
    # The CLI is the one place in probegrid that reaches the HTTP layer (service/), lazily.
    import socket

    from service.main import example_usage, run

    if not 0 < port < 65536:
        raise ValueError(f"--port must be in 1..65535, got {port}")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:  # a busy port is a one-line error here, not uvicorn's log and exit code 3
            probe.bind((host, port))
        except OSError as exc:
            raise ValueError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    base = f"http://{host}:{port}"

    def ready() -> None:  # once the stores have opened
        print(f"viewer: {base}/")
        print(f"serving {', '.join(str(s) for s in stores)} at {base} (docs: {base}/docs)")
        print(example_usage(stores[0], base), flush=True)

    run(stores, host=host, port=port, workers=workers, overrides=limits, on_ready=ready)


def _run_serve(args: argparse.Namespace) -> int:
    limits = {name: getattr(args, name) for name in
              ("request_budget", "header_timeout", "body_timeout")
              if getattr(args, name) is not None}
    _serve(args.stores, args.host, args.port, args.workers, limits)
    return 0


def _stderr_progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


_SUBCOMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (
    _add_filter, _add_bake, _add_info, _add_export, _add_serve, _add_demo,
)


#: A negative number or a comma-separated list starting with one (``-20,0.2,-20,20,2.4,20``,
#: ``-1e-3``, ``-.5,1``): an option's value, never an option (no option starts with a digit).
_NEGATIVE_VALUE = re.compile(r"^-(\d|\.\d)[0-9eE.+\-]*(,[ ]*[-+]?[0-9eE.+\-]*)*$")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``probegrid: error: ...``) and exit code 2.

    argparse takes an argument for an option when it starts with ``-``, unless it is a single
    negative number: ``--bounds -20,0.2,-20,20,2.4,20`` would fail with "expected one
    argument". Negative numbers and comma lists starting with one (:data:`_NEGATIVE_VALUE`) are
    values here, so every comma-separated option (bounds, colours, spacing, positions) works as
    typed.
    """

    def _parse_optional(self, arg_string: str):  # type: ignore[no-untyped-def]
        if _NEGATIVE_VALUE.match(arg_string):
            return None  # a positional string: the value of the option before it
        return super()._parse_optional(arg_string)

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"probegrid: error: {message} (see {self.prog} --help)\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser of the ``probegrid`` command; with ``only`` (a command's name), the
    parser of that command alone (the others' options import modules it does not need)."""
    parser = _Parser(
        prog="probegrid",
        description="Light-probe grids, cube-map environment filtering and a probe map service.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    from probegrid._version import __version__

    parser.add_argument("--version", action="version", version=f"probegrid {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)
    for add in _SUBCOMMANDS if only is None else (_adder(only),):
        add(sub)
    return parser


def _adder(command: str | None) -> Callable[[argparse._SubParsersAction], None] | None:
    """The function that adds ``command``'s parser (None for a name that is no command)."""
    return next((add for add in _SUBCOMMANDS if add.__name__ == f"_add_{command}"), None)


def _command_name(argv: Sequence[str]) -> str | None:
    """The command a command line runs (its first word that is not an option), when it is one
    of the commands; None otherwise (the full parser then reports the error or the help)."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if _adder(word) is not None else None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the exit code."""
    whole_process = argv is None  # the console script's call: this process is the command
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command_name(argv)
    if command == "filter":
        _one_blas_thread()
    parser = build_parser(command)
    args = parser.parse_args(argv)
    code = _dispatch(args)
    if whole_process and command == "filter":
        _exit_now(code)
    return code


def _exit_now(code: int) -> NoReturn:
    """End a finished ``probegrid filter`` process at once, without the interpreter's teardown
    (freeing every module and array one by one: 20 ms of the command's 0.5 s here). Its files
    are closed and on disk by then (the staged output is flushed before it is published), its
    threads have ended, and the standard streams are flushed here."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing more to say
            pass
    os._exit(code)


def _dispatch(args: argparse.Namespace) -> int:
    """Run the parsed command; returns the exit code (module docstring)."""
    from probegrid.errors import ExecutorError

    # SIGTERM stops a command like Ctrl-C does: its cleanup runs (worker processes stopped,
    # temporary files removed; a bake stays resumable)
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return int(args.handler(args))
    except BrokenPipeError:  # the reader went away (``probegrid info S | head``): stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so the exit's flush does not fail again
        return EXIT_BROKEN_PIPE
    except KeyboardInterrupt:
        print("probegrid: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError, ExecutorError) as exc:  # every user-caused error
        if args.debug:
            raise
        print(f"probegrid: error: {_error_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:
        if args.debug:
            raise
        print(f"probegrid: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return EXIT_INTERNAL
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _one_blas_thread() -> None:
    """Start OpenBLAS with one thread when numpy is not loaded yet (a fresh ``probegrid
    filter`` process) and the environment does not say otherwise.

    The filter spends its time in its own threads, each holding BLAS to one thread
    (:func:`probegrid.core.specular.symmetric_zonal_sums`); OpenBLAS's own pool would only be
    started for nothing, which costs 50 ms of the command's start-up here (numpy imports in 80
    instead of 130 ms on this 2-core machine). The variable is read when OpenBLAS loads, and
    removed again once numpy is in, so no child process inherits it. The results are the same
    bits (OpenBLAS splits a product between threads by rows and columns, never along a sum).
    """
    var = "OPENBLAS_NUM_THREADS"
    if "numpy" in sys.modules or var in os.environ:
        return
    os.environ[var] = "1"
    try:
        import numpy  # noqa: F401  (OpenBLAS reads the variable now)
    finally:
        del os.environ[var]


def _error_line(exc: BaseException) -> str:
    """One line for a user-caused error; a settings model's validation error names the option
    (``--face-size: Input should be greater than or equal to 2``) instead of pydantic's
    multi-line report."""
    from probegrid.errors import SettingsError

    if isinstance(exc, SettingsError):
        return f"--{exc.option.replace('_', '-')}: {exc.reason}"
    ValidationError = getattr(sys.modules.get("pydantic"), "ValidationError", ())
    if isinstance(exc, ValidationError) and exc.errors():
        err = exc.errors()[0]
        field = ".".join(str(part) for part in err.get("loc", ()))
        option = f"--{field.replace('_', '-')}" if field else exc.title
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        msg = str(err["msg"]).removeprefix("Value error, ")  # (a validator's own sentence)
        return f"{option}: {msg}{more}"
    if isinstance(exc, OSError) and exc.strerror and type(exc).__str__ is OSError.__str__:
        where = f"{exc.filename}: " if exc.filename else ""  # words, not "[Errno 2] ..."
        return f"{where}{exc.strerror}"
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _terminate(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
