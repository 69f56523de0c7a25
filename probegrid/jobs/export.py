"""Reading a grid store back out: ``probegrid info`` (the manifest in words) and
``probegrid export`` (one probe's maps as image files with the conventions beside them).

Both trust nothing in the store beyond what :func:`probegrid.store.open_store` checks (manifest
schema, file headers and sizes) and refuse, with a one-line :class:`~probegrid.store.StoreError`:
a store without the ``sh`` and ``diffuse`` arrays, map arrays of the wrong per-probe shape,
specular levels that are not ``specular_0 .. specular_<n-1>`` halving in size (level ``k`` has
roughness ``k / (n - 1)``, so a gap would mislabel every level), and, for export, non-finite
values in the exported probe. ``info`` prints manifest fields of unexpected types as they are.
``export`` writes only into a new directory or an earlier export
(:func:`probegrid.jobs.filter.prepare_output_dir`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from probegrid._fs import atomic_write_json
from probegrid._types import CubeLayout, ImageFormat
from probegrid._version import __version__
from probegrid.jobs.filter import prepare_output_dir
from probegrid.store import ProbeStore, StoreError, open_store, partial_path, partial_progress
from probegrid.store.check import map_arrays as _map_arrays
from probegrid.store.check import specular_levels as _specular_levels

__all__ = ["EXPORT_FORMAT", "ExportResult", "describe_store", "export_probe", "parse_probe"]

#: ``format`` of the manifest of an export directory.
EXPORT_FORMAT = "probegrid.probe-export"


def _mb(nbytes: int) -> str:
    return f"{nbytes / 2**20:.1f} MiB"


def _text(value: Any) -> str:
    """A manifest value for a line of text: lists joined by commas, the rest as str."""
    return ", ".join(map(str, value)) if isinstance(value, list) else str(value)


def describe_store(path: str | os.PathLike[str]) -> str:
    """The manifest of a store in words.

    Raises ``StoreError`` (one line) for an unfinished bake, a store :func:`open_store` refuses
    and specular levels that are not ``specular_0 .. specular_<n-1>``; manifest fields of
    unexpected types (``bake.settings`` not a mapping, say) are printed as JSON.
    """
    p = Path(path)
    full = Path(os.path.abspath(p))  # "." has no name to build the partial's name from
    work = full.with_name(full.name + ".work")
    if not full.exists() and (partial_path(full).exists() or work.exists()):
        progress = partial_progress(full) if partial_path(full).exists() else None
        stage = (f"final pass, {progress[0]} of {progress[1]} probes done" if progress
                 else "earlier passes")
        raise StoreError(f"{p} is an unfinished bake ({stage}); run the same bake command "
                         "again to resume it")
    store = open_store(p)
    m = store.manifest
    g = m.grid
    valid = None
    if "valid" in store.names and store.manifest.arrays["valid"].shape == (g.n_probes,):
        valid = np.asarray(store["valid"])
    spec_levels = _specular_levels(store)
    conv = m.conventions
    bake = m.bake.get("settings", {})
    env = m.bake.get("environment", {})
    lines = [
        f"probe grid store {p}",
        (f"  format {m.format} v{m.format_version}, written by probegrid {m.probegrid_version} "
        f"on {m.created:%Y-%m-%d %H:%M:%S} UTC"),
        (f"  grid: {g.label} = {g.n_probes} probes, box {tuple(g.bounds_min)} .. "
        f"{tuple(g.bounds_max)}, spacing {tuple(round(float(s), 6) for s in g.spacing)}"),
        ("  probe (i, j, k) at min + (i, j, k) * (max - min) / (counts - 1); "
        "index = (i * ny + j) * nz + k"),
    ]
    if valid is not None:
        lines.append(f"  valid probes: {int(valid.sum())} of {valid.size}")
    lines.append("  arrays (memory-mappable .npy, probe index first):")
    for name, info in m.arrays.items():
        lines.append(f"    {name:<18} {info.dtype:<8} {tuple(info.shape)!s:<24} "
                     f"{_mb(info.nbytes):>10}  {info.description}")
    if isinstance(bake, dict) and bake:
        lines.append(
            f"  bake: faces {bake.get('face_size')}^2, {bake.get('samples')} sample(s)/texel, "
            f"{bake.get('bounces')} bounce(s), seed {bake.get('seed')}, diffuse "
            f"{bake.get('diffuse_size')}^2, direct light "
            f"{'in the probes' if bake.get('direct') else 'left out'}"
        )
    elif bake:
        lines.append(f"  bake settings: {json.dumps(bake)}")
    filters = m.bake.get("filters", {})
    if isinstance(filters, dict):
        for kind in ("diffuse", "specular"):
            if kind in filters:
                lines.append(f"  {kind} filter: {_text(filters[kind])}")
    elif filters:
        lines.append(f"  filters: {json.dumps(filters)}")
    if env:
        lines.append(f"  environment: {json.dumps(env)}")
    lines.append(f"  scene hash: {m.scene_hash}")
    if m.scene_file is not None:
        lines.append(f"  scene copy: {m.scene_file.file} ({m.scene_file.bytes} bytes, from "
                     f"{m.scene_file.source}; served at /v1/grids/NAME/scene)")
    if spec_levels:
        n = len(spec_levels)
        rough = ", ".join(f"{k}: r={k / (n - 1) if n > 1 else 0:.3g}" for k in spec_levels)
        lines.append(f"  specular levels ({_text(conv.get('roughness_to_mip', ''))}): {rough}")
    for key in ("world_frame", "cube_face_order", "cube_face_storage", "diffuse_map", "sh_basis",
                "sh_coefficients", "color_space", "radiance_units"):
        if key in conv:
            lines.append(f"  {key.replace('_', ' ')}: {_text(conv[key])}")
    if m.quality:
        q = m.quality
        lines.append("  quality:")
        for k, v in q.items():
            lines.append(f"    {k}: {v}")
    return "\n".join(lines)


def parse_probe(text: str, store: ProbeStore) -> tuple[int, int, int]:
    """``"I,J,K"`` -> a probe of the store's grid, with a one-line error when out of range."""
    parts = text.split(",")
    try:
        ijk = tuple(int(x) for x in parts)
    except ValueError:
        raise ValueError(f"--probe must be I,J,K (three integers), got {text!r}") from None
    if len(ijk) != 3:
        raise ValueError(f"--probe must be I,J,K (three integers), got {text!r}")
    counts = store.grid.counts
    if any(not 0 <= a < c for a, c in zip(ijk, counts, strict=True)):
        raise ValueError(f"probe {ijk} is outside the grid {store.grid.label} "
                         f"(0 <= i < {counts[0]}, 0 <= j < {counts[1]}, 0 <= k < {counts[2]})")
    return ijk  # type: ignore[return-value]


def export_probe(
    store_path: str | os.PathLike[str],
    probe: str | tuple[int, int, int],
    out_dir: str | os.PathLike[str],
    *,
    layout: CubeLayout = "faces",
    fmt: ImageFormat = "exr",
    half: bool = False,
) -> ExportResult:
    """Write one probe's maps (diffuse, specular levels, incoming if stored, SH) and a manifest.

    Everything is read and checked before anything is written: a damaged store (missing or
    misshapen arrays, non-contiguous specular levels, non-finite values in this probe) raises
    ``StoreError``, an ``out_dir`` that is not new or an earlier export raises ``ValueError``
    (both one line), and ``half`` with the RGBE ``hdr`` format is refused. The files are
    named as ``probegrid filter`` names them (``diffuse``, ``specular_m<k>``, ``incoming``) and
    written into a staging folder moved into place when complete
    (:mod:`probegrid.jobs.staging`).
    """
    from probegrid.jobs.staging import staged_output

    if fmt == "hdr" and half:
        raise ValueError("--half applies to EXR; Radiance HDR files are always RGBE (8-bit "
                         "mantissas, shared exponent)")
    store = open_store(store_path)
    ijk = parse_probe(probe, store) if isinstance(probe, str) else probe
    index = int(store.probe_index(*ijk))
    maps = _map_arrays(store)
    names = store.names
    data = {name: np.asarray(store[name][index], dtype=np.float32) for name, _, _ in maps}
    data["sh"] = np.asarray(store["sh"][index], dtype=np.float64)
    if "positions" in names:
        data["positions"] = np.asarray(store["positions"][index], dtype=np.float64)
    bad = {name: int(np.count_nonzero(~np.isfinite(a))) for name, a in data.items()}
    bad = {name: count for name, count in bad.items() if count}
    if bad:
        where = ", ".join(f"{count} in {name!r}" for name, count in bad.items())
        raise StoreError(f"probe {tuple(ijk)} of {store.path} holds non-finite values (NaN or "
                         f"inf): {where}; the store is damaged")

    out = prepare_output_dir(out_dir, EXPORT_FORMAT, create=False)
    with staged_output(out, lambda final: prepare_output_dir(final, EXPORT_FORMAT,
                                                             create=False)) as stage:
        written = _write_export(stage, store, store_path, ijk, index, maps, data, layout=layout,
                                fmt=fmt, half=half)
    return ExportResult([out / p.relative_to(stage) for p in written],
                        probe=tuple(ijk), valid=_probe_valid(store, index))


class ExportResult(list[Path]):
    """The files :func:`export_probe` wrote (a list of Path), the probe and whether it is valid.

    ``valid`` is False for a probe the bake marked invalid (inside geometry: its maps hold the
    inside of a wall), None when the store records no validity.
    """

    def __init__(self, paths: list[Path], *, probe: tuple[int, ...], valid: bool | None) -> None:
        super().__init__(paths)
        self.probe = probe
        self.valid = valid


def _probe_valid(store: ProbeStore, index: int) -> bool | None:
    if "valid" in store.names and store.manifest.arrays["valid"].shape == (store.n_probes,):
        return bool(store["valid"][index])
    return None


def _write_export(out: Path, store: ProbeStore, store_path: str | os.PathLike[str],
                  ijk: tuple[int, ...], index: int, maps: list[tuple[str, str, int | None]],
                  data: dict[str, Any], *, layout: CubeLayout, fmt: ImageFormat,
                  half: bool) -> list[Path]:
    """Write the probe's files into (staging) directory ``out``; returns their paths."""
    from probegrid import imageio
    from probegrid.core.conventions import conventions

    n_levels = sum(kind == "specular" for _, kind, _ in maps)
    manifest_path = out / "manifest.json"
    conv = conventions()
    meta = {"probegrid:conventions": json.dumps(conv), "probegrid:version": __version__,
            "probegrid:probe": json.dumps(list(ijk))}
    files: list[dict[str, Any]] = []
    written: list[Path] = []
    for name, kind, level in maps:
        faces = data[name]
        # files named as probegrid filter names them: specular_m<k>, diffuse, incoming
        stem = f"specular_m{level}" if kind == "specular" else name
        paths = imageio.write_cube(out / stem, faces, layout=layout, fmt=fmt, half=half,
                                   metadata={**meta, "probegrid:kind": kind})
        written += paths
        r = None if level is None else (level / (n_levels - 1) if n_levels > 1 else 0.0)
        files.append({"path": [str(q.relative_to(out)) for q in paths], "kind": kind,
                      "level": level, "roughness": r, "layout": layout, "format": fmt,
                      "dtype": paths.pixel_type, "face_size": int(faces.shape[1])})
    atomic_write_json(out / "sh.json", {"coefficients": data["sh"].tolist(),
                                        "basis": conv["sh_basis"],
                                        "content": conv["sh_coefficients"]})
    files.append({"path": "sh.json", "kind": "sh", "level": None, "roughness": None})
    written.append(out / "sh.json")
    position = data["positions"].tolist() if "positions" in data else None
    valid = _probe_valid(store, index)
    atomic_write_json(manifest_path, {
        "format": EXPORT_FORMAT, "format_version": 1,
        "probegrid_version": __version__, "store": str(Path(store_path)),
        "probe": {"ijk": list(ijk), "index": index, "position": position, "valid": valid},
        "conventions": conv, "files": files,
    })
    written.append(manifest_path)
    return written
