"""The ``probegrid`` command line.

Sub-commands parse their options into the settings objects of the library and call it; no
numerical work happens here. Every failure the user can cause (a bad file, a bad option value, a
non-finite pixel) ends with one line ``probegrid: error: ...`` on stderr and a non-zero exit code
(2 for bad input, 130 for an interrupt); ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn

__all__ = ["build_parser", "main"]

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
EXIT_INTERNAL = 1
#: Exit code when stdout's reader went away (as a process killed by SIGPIPE).
EXIT_BROKEN_PIPE = 141


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _finite_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _add_filter(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "filter",
        help="filter an HDR environment into diffuse and specular maps",
        description=(
            "Read one HDR environment (or six face files) and write its diffuse map "
            "(irradiance/pi), GGX specular mip chain, SH coefficients, the DFG LUT, PNG previews "
            "and manifest.json into --out."
        ),
    )
    p.add_argument("env", nargs="+", type=Path, help="environment image, or six face files")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument(
        "--layout",
        default="auto",
        choices=["auto", "equirect", "angular", "hcross", "vcross", "faces"],
        help="input layout (default: detected from the aspect ratio)",
    )
    p.add_argument("--size", type=_positive_int, help="cube face size of the specular level 0")
    p.add_argument("--diffuse-size", type=_positive_int, default=32, help="diffuse face size")
    p.add_argument(
        "--diffuse-method", choices=["sh", "exact"], default="exact",
        help="exact clamped-cosine integral (default) or via SH coefficients (--sh-bands)",
    )
    p.add_argument(
        "--diffuse-source-size", type=_positive_int,
        help="face size the exact diffuse sum reads (the cube's box mip; default: the cube up to "
             "128, the 128 mip of larger cubes)",
    )
    p.add_argument("--specular-levels", type=_positive_int, help="mip levels (default: full chain)")
    p.add_argument(
        "--specular-method", choices=["tiered", "fis", "exact"], default="tiered",
        help="GGX prefilter: tiered exact-kernel convolution (default), filtered importance "
             "sampling, or the brute-force exact convolution (slow)",
    )
    p.add_argument("--samples", type=_positive_int,
                   help="samples per texel for --specular-method fis")
    p.add_argument(
        "--sh-bands", type=_positive_int, default=3,
        help="SH bands for sh.json and --diffuse-method sh (default 3 = 9 coefficients; up to 16)",
    )
    p.add_argument(
        "--sh-window", choices=["none", "hanning", "lanczos", "gauss", "auto"], default="none",
        help="SH windowing against ringing (auto: the least that makes irradiance >= 0)",
    )
    p.add_argument("--sh-window-width", type=_finite_float, help="window width (bands)")
    p.add_argument("--format", choices=["exr", "hdr"], default="exr", help="map file format")
    p.add_argument("--float", action="store_true", help="write float32 EXR instead of half")
    p.add_argument(
        "--output-layout", choices=["faces", "hcross", "vcross", "equirect"], default="faces",
        help="layout of the written maps",
    )
    p.add_argument(
        "--seam", choices=["none", "average", "border"], default="none",
        help="seam export mode for consumers without seamless cube filtering",
    )
    p.add_argument(
        "--clamp", type=_finite_float,
        help="clamp radiance to [0, CLAMP]; NaN becomes 0 (otherwise non-finite pixels are an error)",
    )
    p.add_argument("--lut-size", type=_positive_int, default=128, help="DFG LUT size")
    p.add_argument("--no-previews", action="store_true", help="skip the PNG previews")
    p.set_defaults(handler=_run_filter)


def _run_filter(args: argparse.Namespace) -> int:
    from probegrid.filterjob import FilterSettings, run_filter

    settings = FilterSettings(
        layout=args.layout,
        size=args.size,
        diffuse_size=args.diffuse_size,
        diffuse_method=args.diffuse_method,
        diffuse_source_size=args.diffuse_source_size,
        specular_levels=args.specular_levels,
        specular_method=args.specular_method,
        samples=args.samples,
        sh_bands=args.sh_bands,
        sh_window=args.sh_window,
        sh_window_width=args.sh_window_width,
        format=args.format,
        half=not args.float,
        output_layout=args.output_layout,
        seam=args.seam,
        clamp=args.clamp,
        lut_size=args.lut_size,
        previews=not args.no_previews,
    )
    result = run_filter(args.env, args.out, settings, progress=_stderr_progress)
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
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output directory")
    p.add_argument("--no-serve", action="store_true", help="stop after filtering and baking")
    p.add_argument("--port", type=int, default=8000)
    p.set_defaults(handler=_run_demo)


def _run_demo(args: argparse.Namespace) -> int:
    from probegrid.demo import run_demo

    print(run_demo(args.out, progress=_stderr_progress), flush=True)
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
    g = p.add_mutually_exclusive_group()
    g.add_argument("--grid", help="probe counts NXxNYxNZ (default: 8 along the longest axis)")
    g.add_argument("--spacing", help="probes exactly S (or SX,SY,SZ) apart, centred in the box "
                   "(scene units)")
    p.add_argument("--bounds", help="grid box x0,y0,z0,x1,y1,z1 (default: the scene bounds, "
                   "probes at the centres of the grid's cells)")
    p.add_argument("--margin", type=_finite_float,
                   help="grow (or, negative, shrink) the scene bounds by this much")
    p.add_argument("--environment", type=Path, nargs="+", metavar="FILE",
                   help="HDR environment: one image (any layout) or six face files")
    p.add_argument("--environment-layout", default="auto",
                   choices=["auto", "equirect", "angular", "hcross", "vcross"])
    p.add_argument("--environment-color", help="constant environment radiance R,G,B")
    p.add_argument("--environment-intensity", type=_finite_float, default=1.0)
    p.add_argument("--environment-rotation", type=_finite_float, default=0.0,
                   help="degrees about +Y (right-handed)")
    p.add_argument("--face-size", type=_positive_int, default=32, help="incoming cube face size")
    p.add_argument("--bounces", type=int, default=2, help="indirect bounces (default 2)")
    p.add_argument("--samples", type=_positive_int, default=1, help="rays per texel")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--diffuse-size", type=_positive_int, default=8)
    p.add_argument("--specular-levels", type=_positive_int)
    p.add_argument("--no-direct", action="store_true",
                   help="leave the punctual lights' direct light out of the probes")
    p.add_argument("--store-incoming", action="store_true", help="also store the raw cubes")
    p.add_argument("--no-relocate", action="store_true",
                   help="do not move probes that are inside geometry")
    p.add_argument("--batch-size", type=_positive_int, default=8, help="probes per task")
    x = p.add_mutually_exclusive_group()
    x.add_argument("--workers", type=_positive_int, help="local worker processes (default: all)")
    x.add_argument("--scheduler", help="Dask scheduler address, e.g. tcp://HOST:8786")
    p.add_argument("--overwrite", action="store_true", help="replace an existing store")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(handler=_run_bake)


def _run_bake(args: argparse.Namespace) -> int:
    from probegrid.bakejob import BakeOptions, run_bake

    opts = BakeOptions(**{k: v for k, v in vars(args).items() if k not in ("handler", "debug",
                                                                           "command")})
    report = run_bake(opts)
    print(report.summary())
    print(f"look at it: probegrid info {args.out}   |   probegrid export {args.out} "
          f"--probe 0,0,0 --out {args.out.with_suffix('')}-probe")
    return 0


def _add_info(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="print a store's manifest in words")
    p.add_argument("store", type=Path)
    p.set_defaults(handler=_run_info)


def _run_info(args: argparse.Namespace) -> int:
    from probegrid.export import describe_store

    print(describe_store(args.store))
    return 0


def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write one probe's maps as image files")
    p.add_argument("store", type=Path)
    p.add_argument("--probe", required=True, help="I,J,K")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--layout", choices=["faces", "hcross", "vcross", "equirect"],
                   default="faces")
    p.add_argument("--format", choices=["exr", "hdr"], default="exr")
    p.add_argument("--half", action="store_true", help="half-float EXR")
    p.set_defaults(handler=_run_export)


def _run_export(args: argparse.Namespace) -> int:
    from probegrid.export import export_probe

    written = export_probe(args.store, args.probe, args.out, layout=args.layout,
                           fmt=args.format, half=args.half)
    print(f"wrote {len(written)} files to {args.out}/ (manifest.json lists them with the "
          "conventions)")
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
    p.add_argument("stores", nargs="+", type=Path, metavar="STORE")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=_positive_int, default=1, help="uvicorn worker processes")
    p.set_defaults(handler=_run_serve)


def _serve(stores: Sequence[Path], host: str, port: int, workers: int) -> None:
    # The CLI is the one place in probegrid that reaches the HTTP layer (service/), lazily.
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
        print(f"serving {', '.join(str(s) for s in stores)} at {base} (docs: {base}/docs)")
        print(example_usage(stores[0], base), flush=True)

    run(stores, host=host, port=port, workers=workers, on_ready=ready)


def _run_serve(args: argparse.Namespace) -> int:
    _serve(args.stores, args.host, args.port, args.workers)
    return 0


def _stderr_progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


_SUBCOMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (
    _add_filter, _add_bake, _add_info, _add_export, _add_serve, _add_demo,
)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``probegrid: error: ...``) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"probegrid: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``probegrid`` command."""
    parser = _Parser(
        prog="probegrid",
        description="Light-probe grids, cube-map environment filtering and a probe map service.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)
    for add in _SUBCOMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the exit code."""
    from probegrid.executors import ExecutorError

    parser = build_parser()
    args = parser.parse_args(argv)
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


def _error_line(exc: BaseException) -> str:
    """One line for a user-caused error; a settings model's validation error names the option
    (``--face-size: Input should be greater than or equal to 2``) instead of pydantic's
    multi-line report."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError) and exc.errors():
        err = exc.errors()[0]
        field = ".".join(str(part) for part in err.get("loc", ()))
        option = f"--{field.replace('_', '-')}" if field else exc.title
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        return f"{option}: {err['msg']}{more}"
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _terminate(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
