"""Reading a grid store back out: ``probegrid info`` (the manifest in words) and
``probegrid export`` (one probe's maps as image files with PNG previews and the conventions
beside them, or many probes' at once: ``--probe all`` or a box ``I0,J0,K0:I1,J1,K1``, a folder
per probe). Every ``sh.json`` holds the probe's deringed SH by default (:func:`read_sh`: the
irradiance non-negative everywhere, as the service's ``/sh`` answers; ``sh="raw"`` the stored
projection) with the consumers' forms (:func:`sh_document`); the manifest says which.

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
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid._fs import atomic_write_json
from probegrid._types import CubeLayout, ImageFormat, SHKind
from probegrid._version import __version__
from probegrid.jobs.filter import prepare_output_dir
from probegrid.store import (
    BakeInputs,
    ProbeStore,
    StoreError,
    open_store,
    partial_path,
    partial_progress,
)
from probegrid.store.check import map_arrays as _map_arrays
from probegrid.store.check import specular_levels as _specular_levels

__all__ = ["EXPORT_FORMAT", "EXPORT_MANY_FORMAT", "SH_MEANING", "ExportResult", "ProbesExport",
           "describe_store", "export_probe", "export_probes", "parse_probe", "parse_probes",
           "read_sh"]

#: ``format`` of the manifest of an export directory.
EXPORT_FORMAT = "probegrid.probe-export"
#: ``format`` of the manifest of a many-probe export (``--probe all`` or a box).
EXPORT_MANY_FORMAT = "probegrid.probes-export"
_SPECULAR_RE = re.compile(r"^specular_(0|[1-9][0-9]*)$")

#: What each kind of exported SH is (``sh`` of every export's manifest and ``sh.json``).
SH_MEANING: dict[str, str] = {
    "deringed": ("deringed: each probe's radiance SH windowed so that its irradiance is "
                 "non-negative over the whole sphere (the store's sh_deringed; equal to the raw "
                 "projection where that already holds), as the service's /sh answers by "
                 "default; a consumer that clamps negative irradiance (three.js) then shows "
                 "no black patches"),
    "raw": ("raw: the store's least-squares SH projection of each probe (may ring: negative "
            "irradiance opposite a bright light)"),
}


def sh_document(coefficients: NDArray[np.float64], kind: str, conv: dict[str, Any], *,
                order: str | None = None) -> dict[str, Any]:
    """An export's ``sh.json``: the radiance coefficients (``(9, 3)`` or ``(P, 9, 3)``), which
    kind they are, their basis, and the same SH in each consumer's form
    (:func:`probegrid.export.shforms.sh_forms`), as the filter's ``sh.json`` carries them."""
    from probegrid.export.shforms import sh_forms

    doc: dict[str, Any] = {"coefficients": coefficients.tolist(), "sh": kind,
                           "sh_meaning": SH_MEANING[kind], "basis": conv["sh_basis"],
                           "content": conv["sh_coefficients"]}
    if order is not None:
        doc["order"] = order
    doc["consumers"] = sh_forms(coefficients)
    return doc


def read_sh(store: ProbeStore, kind: SHKind = "deringed", *,
            index: int | None = None, valid: NDArray[np.bool_] | None = None
            ) -> NDArray[np.float64]:
    """The radiance SH an export writes: ``(P, 9, 3)``, or ``(9, 3)`` of probe ``index``.

    ``kind="deringed"`` (the default of every export) reads the store's ``sh_deringed`` extra,
    or, for a store without it (format 1), windows the raw SH here
    (:func:`probegrid.core.sh.dering.dering`; only the ``valid`` probes of a whole grid, the
    others being replaced by the exports anyway); ``"raw"`` the stored projection.
    """
    if kind not in SH_MEANING:
        raise ValueError(f"--sh must be one of {', '.join(SH_MEANING)}, got {kind!r}")
    select = slice(None) if index is None else index
    if kind == "deringed" and "sh_deringed" in store.extras:
        return np.asarray(store["sh_deringed"][select], dtype=np.float64)
    raw = np.array(store["sh"][select], dtype=np.float64)
    if kind == "raw":
        return raw
    from probegrid.core.sh.dering import dering

    if index is not None:
        return dering(raw[None])[0][0]
    rows = np.isfinite(raw).all(axis=(1, 2))
    if valid is not None:
        rows &= np.asarray(valid, dtype=bool)
    if rows.any():
        raw[rows] = dering(raw[rows])[0]
    return raw


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
    valid = store.valid_mask()
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
    if m.inputs is not None:
        lines.extend(_input_lines(m.inputs))
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


def _input_lines(inputs: BakeInputs) -> list[str]:
    """``info``'s lines for the scene and environment as given (manifest ``inputs``)."""
    sc, env = inputs.scene, inputs.environment

    def count(n: int, what: str) -> str:
        return f"{n:,} {what}" if n == 1 else f"{n:,} {what}{'es' if what == 'mesh' else 's'}"

    parts = [count(sc.triangles, "triangle")]
    if sc.meshes is not None:
        parts.append(count(sc.meshes, "mesh"))
    parts += [count(sc.materials, "material"),
              count(sc.emissive_materials, "emissive material"),
              count(sc.punctual_lights, "punctual light")]
    lines = [(f"  scene as given: {sc.name} ({sc.bytes:,} bytes): {', '.join(parts)}; "
              f"hash {sc.content_hash}")]
    if sc.unhonoured:
        lines.append(f"  not honoured by the bake: {'; '.join(sc.unhonoured)}")
    if env.layout == "none":
        what = "none (black)"
    elif env.layout == "color":
        assert env.color is not None
        what = "color " + ",".join(f"{c:g}" for c in env.color)
    else:
        assert env.pixel_size is not None
        w, h = env.pixel_size
        if env.layout == "faces":
            what = (f"faces {', '.join(env.files)} (+X, -X, +Y, -Y, +Z, -Z; {w}x{h} each, "
                    f"{env.bytes:,} bytes)")
        else:
            what = f"{env.files[0]} ({env.layout} {w}x{h}, {env.bytes:,} bytes)"
    extra = ""
    if env.layout != "none" and (env.intensity != 1.0 or env.rotation_deg != 0.0):
        extra = f", intensity {env.intensity:g}, rotated {env.rotation_deg:g} deg about +Y"
    lines.append(f"  environment as given: {what}{extra}; hash {env.content_hash}")
    return lines


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


def parse_probes(text: str, store: ProbeStore) -> list[tuple[int, int, int]]:
    """``"all"``, a box ``"I0,J0,K0:I1,J1,K1"`` (both corners included) or ``"I,J,K"`` -> the
    selected probes in store order, with a one-line error for anything else."""
    t = text.strip()
    nx, ny, nz = store.grid.counts
    if t == "all":
        lo, hi = (0, 0, 0), (nx - 1, ny - 1, nz - 1)
    elif ":" in t:
        a, _, b = t.partition(":")
        try:
            lo, hi = parse_probe(a, store), parse_probe(b, store)
        except ValueError as e:
            raise ValueError(f"--probe box {text!r}: {e}") from None
        if any(x > y for x, y in zip(lo, hi, strict=True)):
            raise ValueError(f"--probe box {text!r}: the first corner must not exceed the second "
                             "in any of i, j, k")
    else:
        return [parse_probe(t, store)]
    return [(i, j, k) for i in range(lo[0], hi[0] + 1) for j in range(lo[1], hi[1] + 1)
            for k in range(lo[2], hi[2] + 1)]


def _read_probes(store: ProbeStore, maps: list[tuple[str, str, int | None]],
                 probes: list[tuple[int, int, int]]) -> list[int]:
    """The store indices of ``probes``, after checking every exported value of them is finite
    (``StoreError`` naming the first damaged probe). Reads a bounded number of probes at once."""
    indices = [int(store.probe_index(*ijk)) for ijk in probes]
    idx = np.asarray(indices, dtype=np.intp)
    names = [name for name, _, _ in maps] + ["sh"] + (["positions"] if "positions" in store.names
                                                      else [])
    for name in names:
        per = int(np.prod(store.manifest.arrays[name].shape[1:])) * 4
        step = max(1, (64 << 20) // max(per, 1))  # ~64 MB per read
        for c in range(0, idx.size, step):
            block = np.asarray(store[name][idx[c:c + step]])
            finite = np.isfinite(block.reshape(block.shape[0], -1))
            ok = finite.all(axis=1)
            if not ok.all():
                first = int(np.argmin(ok))
                count = int(np.count_nonzero(~finite[first]))
                raise StoreError(f"probe {probes[c + first]} of {store.path} holds non-finite "
                                 f"values (NaN or inf): {count} in {name!r}; the store is "
                                 "damaged")
    return indices


def _write_probe(out: Path, store: ProbeStore, maps: list[tuple[str, str, int | None]],
                 index: int, ijk: tuple[int, int, int], conv: dict[str, Any], *,
                 layout: CubeLayout, fmt: ImageFormat, half: bool,
                 previews: bool, sh_kind: SHKind) -> tuple[list[dict[str, Any]], list[Path]]:
    """One probe's maps, ``sh.json`` (the ``sh_kind`` SH, :func:`sh_document`) and
    (``previews``) PNG previews into ``out``."""
    from probegrid import imageio
    from probegrid.jobs.filter import _specular_sheet

    n_levels = sum(kind == "specular" for _, kind, _ in maps)
    meta = {"probegrid:conventions": json.dumps(conv), "probegrid:version": __version__,
            "probegrid:probe": json.dumps(list(ijk))}
    files: list[dict[str, Any]] = []
    written: list[Path] = []
    data: dict[str, np.ndarray] = {}
    for name, kind, level in maps:
        faces = data[name] = np.asarray(store[name][index], dtype=np.float32)
        # files named as probegrid filter names them: specular_m<k>, diffuse, incoming
        stem = f"specular_m{level}" if kind == "specular" else name
        paths = imageio.write_cube(out / stem, faces, layout=layout, fmt=fmt, half=half,
                                   metadata={**meta, "probegrid:kind": kind})
        written += paths
        r = None if level is None else (level / (n_levels - 1) if n_levels > 1 else 0.0)
        files.append({"path": [str(q.relative_to(out)) for q in paths], "kind": kind,
                      "level": level, "roughness": r, "layout": layout, "format": fmt,
                      "dtype": paths.pixel_type, "face_size": int(faces.shape[1])})
    atomic_write_json(out / "sh.json", sh_document(read_sh(store, sh_kind, index=index),
                                                   sh_kind, conv))
    files.append({"path": "sh.json", "kind": "sh", "level": None, "roughness": None,
                  "sh": sh_kind})
    written.append(out / "sh.json")
    if previews:  # as filter's: each tone-mapped by its own statistics
        from probegrid.core.color import PREVIEW_TONE_MAPPING

        shown = [("diffuse", data["diffuse"])]
        if n_levels:
            shown.append(("specular", _specular_sheet([data[f"specular_{k}"]
                                                       for k in range(n_levels)])))
        if "incoming" in data:
            shown.append(("incoming", data["incoming"]))
        for what, img in shown:
            path = out / f"preview_{what}.png"
            imageio.write_preview_png(path, img)
            files.append({"path": path.name, "kind": "preview", "of": what, "level": None,
                          "roughness": None, "format": "png",
                          "tone_mapping": PREVIEW_TONE_MAPPING,
                          "layout": "hcross per level, level 0 at the top"
                          if what == "specular" else "hcross"})
            written.append(path)
    return files, written


def export_probe(
    store_path: str | os.PathLike[str],
    probe: str | tuple[int, int, int],
    out_dir: str | os.PathLike[str],
    *,
    layout: CubeLayout = "faces",
    fmt: ImageFormat = "exr",
    half: bool = False,
    previews: bool = True,
    sh: SHKind = "deringed",
) -> ExportResult:
    """Write one probe's maps (diffuse, specular levels, incoming if stored, the ``sh`` kind of
    SH: deringed by default, :func:`read_sh`), PNG previews (unless ``previews`` is false) and
    a manifest.

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
    if sh not in SH_MEANING:
        raise ValueError(f"--sh must be one of {', '.join(SH_MEANING)}, got {sh!r}")
    store = open_store(store_path)
    ijk = parse_probe(probe, store) if isinstance(probe, str) else probe
    maps = _map_arrays(store)
    index = _read_probes(store, maps, [ijk])[0]

    out = prepare_output_dir(out_dir, EXPORT_FORMAT, create=False)
    with staged_output(out, lambda final: prepare_output_dir(final, EXPORT_FORMAT,
                                                             create=False)) as stage:
        written = _write_export(stage, store, store_path, ijk, index, maps, layout=layout,
                                fmt=fmt, half=half, previews=previews, sh_kind=sh)
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
    valid = store.valid_mask()
    return None if valid is None else bool(valid[index])


def _write_export(out: Path, store: ProbeStore, store_path: str | os.PathLike[str],
                  ijk: tuple[int, ...], index: int, maps: list[tuple[str, str, int | None]],
                  *, layout: CubeLayout, fmt: ImageFormat, half: bool,
                  previews: bool, sh_kind: SHKind) -> list[Path]:
    """Write the probe's files into (staging) directory ``out``; returns their paths."""
    from probegrid.core.conventions import conventions

    manifest_path = out / "manifest.json"
    conv = conventions()
    files, written = _write_probe(out, store, maps, index, ijk, conv, layout=layout, fmt=fmt,
                                  half=half, previews=previews, sh_kind=sh_kind)
    position = (np.asarray(store["positions"][index], dtype=np.float64).tolist()
                if "positions" in store.names else None)
    valid = _probe_valid(store, index)
    atomic_write_json(manifest_path, {
        "format": EXPORT_FORMAT, "format_version": 1,
        "probegrid_version": __version__, "store": str(Path(store_path)),
        "probe": {"ijk": list(ijk), "index": index, "position": position, "valid": valid},
        "sh": {"kind": sh_kind, "meaning": SH_MEANING[sh_kind]},
        "conventions": conv, "files": files,
    })
    written.append(manifest_path)
    return written


@dataclass
class ProbesExport:
    """What :func:`export_probes` wrote."""

    out_dir: Path
    probes: list[tuple[int, int, int]]
    invalid: list[tuple[int, int, int]]
    files: int

    def summary(self) -> str:
        """One line, plus the invalid probes when there are any."""
        line = (f"wrote {len(self.probes)} probe{'s' if len(self.probes) != 1 else ''} "
                f"({self.files} files) to {self.out_dir}/, one folder I_J_K each "
                "(manifest.json lists them with the conventions)")
        if self.invalid:
            shown = ", ".join(",".join(map(str, p)) for p in self.invalid[:20])
            more = f" and {len(self.invalid) - 20} more" if len(self.invalid) > 20 else ""
            line += (f"\n  {len(self.invalid)} of them invalid (inside geometry; exported as "
                     f"baked, not filled): {shown}{more}")
        return line


def export_probes(
    store_path: str | os.PathLike[str],
    selection: str,
    out_dir: str | os.PathLike[str],
    *,
    layout: CubeLayout = "faces",
    fmt: ImageFormat = "exr",
    half: bool = False,
    previews: bool = True,
    sh: SHKind = "deringed",
) -> ProbesExport:
    """Many probes' maps at once (``selection``: ``all``, ``I0,J0,K0:I1,J1,K1`` or ``I,J,K``):
    a folder ``I_J_K`` per probe holding what :func:`export_probe` writes plus PNG previews
    (``preview_diffuse.png``, ``preview_specular.png``, ``preview_incoming.png``), and one
    ``manifest.json`` listing every probe with its position and validity. Checked first like
    :func:`export_probe` (every selected probe's values must be finite)."""

    if sh not in SH_MEANING:
        raise ValueError(f"--sh must be one of {', '.join(SH_MEANING)}, got {sh!r}")
    store = open_store(store_path)
    probes = parse_probes(selection, store)
    maps = _map_arrays(store)
    indices = _read_probes(store, maps, probes)
    valid = store.valid_mask()
    positions = (np.asarray(store["positions"], dtype=np.float64)
                 if "positions" in store.names else None)

    from probegrid.jobs.staging import staged_output

    out = prepare_output_dir(out_dir, EXPORT_MANY_FORMAT, create=False)
    with staged_output(out, lambda final: prepare_output_dir(final, EXPORT_MANY_FORMAT,
                                                             create=False)) as stage:
        count, invalid = _write_many(stage, store, store_path, selection, probes, indices, maps,
                                     valid, positions, layout=layout, fmt=fmt, half=half,
                                     previews=previews, sh_kind=sh)
    return ProbesExport(out, probes, invalid, count)


def _write_many(out: Path, store: ProbeStore, store_path: str | os.PathLike[str], selection: str,
                probes: list[tuple[int, int, int]], indices: list[int],
                maps: list[tuple[str, str, int | None]], valid: NDArray[np.bool_] | None,
                positions: NDArray[np.float64] | None, *, layout: CubeLayout, fmt: ImageFormat,
                half: bool, previews: bool,
                sh_kind: SHKind) -> tuple[int, list[tuple[int, int, int]]]:
    """Write :func:`export_probes`' folders and manifest into (staging) directory ``out``;
    returns the number of files and the invalid probes."""
    from probegrid.core.conventions import conventions

    conv = conventions()
    entries: list[dict[str, Any]] = []
    count = 0
    for ijk, index in zip(probes, indices, strict=True):
        sub = out / "_".join(map(str, ijk))
        sub.mkdir(exist_ok=True)
        files, written = _write_probe(sub, store, maps, index, ijk, conv, layout=layout,
                                      fmt=fmt, half=half, previews=previews,
                                      sh_kind=sh_kind)
        count += len(written)
        entries.append({"ijk": list(ijk), "index": index, "folder": sub.name,
                        "position": None if positions is None else positions[index].tolist(),
                        "valid": None if valid is None else bool(valid[index]),
                        "files": files})
    invalid = [ijk for ijk, index in zip(probes, indices, strict=True)
               if valid is not None and not valid[index]]
    atomic_write_json(out / "manifest.json", {
        "format": EXPORT_MANY_FORMAT, "format_version": 1,
        "probegrid_version": __version__, "store": str(Path(store_path)),
        "selection": selection, "count": len(probes),
        "invalid": [list(p) for p in invalid],
        "sh": {"kind": sh_kind, "meaning": SH_MEANING[sh_kind]},
        "conventions": conv, "probes": entries,
    })
    return count + 1, invalid
