"""Reading a grid store back out: ``probegrid info`` (the manifest in words) and
``probegrid export`` (one probe's maps as image files with the conventions beside them).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Literal

import numpy as np

from probegrid import __version__
from probegrid.filterjob import write_json_atomic
from probegrid.store import ProbeStore, StoreError, open_store, partial_path, partial_progress

__all__ = ["describe_store", "export_probe", "parse_probe"]


def _mb(nbytes: int) -> str:
    return f"{nbytes / 2**20:.1f} MiB"


def _specular_levels(store: ProbeStore) -> list[int]:
    """The levels ``k`` of the store's ``specular_<k>`` arrays, ascending."""
    return sorted(int(n.split("_")[1]) for n in store.names if n.startswith("specular_"))


def describe_store(path: str | os.PathLike[str]) -> str:
    """The manifest of a store in words (raises ``StoreError`` for an unfinished bake)."""
    p = Path(path)
    work = p.with_name(p.name + ".work")
    if not p.exists() and (partial_path(p).exists() or work.exists()):
        progress = partial_progress(p) if partial_path(p).exists() else None
        stage = (f"final pass, {progress[0]} of {progress[1]} probes done" if progress
                 else "earlier passes")
        raise StoreError(f"{p} is an unfinished bake ({stage}); run the same bake command "
                         "again to resume it")
    store = open_store(p)
    m = store.manifest
    g = m.grid
    valid = np.asarray(store["valid"]) if "valid" in store.names else None
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
    if bake:
        lines.append(
            f"  bake: faces {bake.get('face_size')}^2, {bake.get('samples')} sample(s)/texel, "
            f"{bake.get('bounces')} bounce(s), seed {bake.get('seed')}, diffuse "
            f"{bake.get('diffuse_size')}^2, direct light "
            f"{'in the probes' if bake.get('direct') else 'left out'}"
        )
    filters = m.bake.get("filters", {})
    for kind in ("diffuse", "specular"):
        if kind in filters:
            lines.append(f"  {kind} filter: {filters[kind]}")
    if env:
        lines.append(f"  environment: {json.dumps(env)}")
    lines.append(f"  scene hash: {m.scene_hash}")
    if spec_levels:
        n = len(spec_levels)
        rough = ", ".join(f"{k}: r={k / (n - 1) if n > 1 else 0:.3g}" for k in spec_levels)
        lines.append(f"  specular levels ({conv.get('roughness_to_mip', '')}): {rough}")
    for key in ("world_frame", "cube_face_order", "cube_face_storage", "diffuse_map", "sh_basis",
                "sh_coefficients", "color_space", "radiance_units"):
        if key in conv:
            val = conv[key]
            lines.append(f"  {key.replace('_', ' ')}: "
                         f"{', '.join(val) if isinstance(val, list) else val}")
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
    layout: Literal["faces", "hcross", "vcross", "equirect"] = "faces",
    fmt: Literal["exr", "hdr"] = "exr",
    half: bool = False,
) -> list[Path]:
    """Write one probe's maps (diffuse, specular levels, incoming if stored, SH) and a manifest."""
    from probegrid import imageio
    from probegrid.conventions import conventions

    store = open_store(store_path)
    ijk = parse_probe(probe, store) if isinstance(probe, str) else probe
    index = int(store.probe_index(*ijk))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    manifest_path = out / "manifest.json"
    if manifest_path.exists():
        manifest_path.unlink()
    conv = conventions()
    meta = {"probegrid:conventions": json.dumps(conv), "probegrid:version": __version__,
            "probegrid:probe": json.dumps(list(ijk))}
    files: list[dict[str, Any]] = []
    written: list[Path] = []
    names = store.names
    levels = _specular_levels(store)
    maps = [("diffuse", "diffuse", None)]
    maps += [(f"specular_{k}", "specular", k) for k in levels]
    if "incoming" in names:
        maps.append(("incoming", "incoming", None))
    for name, kind, level in maps:
        faces = np.asarray(store[name][index], dtype=np.float32)
        paths = imageio.write_cube(out / name, faces, layout=layout, fmt=fmt, half=half,
                                   metadata={**meta, "probegrid:kind": kind})
        written += paths
        r = None if level is None else (level / (len(levels) - 1) if len(levels) > 1 else 0.0)
        files.append({"path": [str(q.relative_to(out)) for q in paths], "kind": kind,
                      "level": level, "roughness": r, "layout": layout, "format": fmt,
                      "face_size": int(faces.shape[1])})
    coeffs = np.asarray(store["sh"][index], dtype=np.float64)
    write_json_atomic(out / "sh.json", {"coefficients": coeffs.tolist(),
                                        "basis": conv["sh_basis"],
                                        "content": conv["sh_coefficients"]})
    files.append({"path": "sh.json", "kind": "sh", "level": None, "roughness": None})
    written.append(out / "sh.json")
    position = np.asarray(store["positions"][index]).tolist() if "positions" in names else None
    valid = bool(store["valid"][index]) if "valid" in names else None
    write_json_atomic(manifest_path, {
        "format": "probegrid.probe-export", "format_version": 1,
        "probegrid_version": __version__, "store": str(Path(store_path)),
        "probe": {"ijk": list(ijk), "index": index, "position": position, "valid": valid},
        "conventions": conv, "files": files,
    })
    written.append(manifest_path)
    return written
