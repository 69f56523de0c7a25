"""The probe volume a glTF scene marks with a node: its box in world space, found by name.

Engines place an irradiance volume with an empty node: Bevy's ``LightProbe`` (and its
``IrradianceVolume``) covers **the unit cube from -0.5 to 0.5 on every axis, transformed by the
entity's world transform**; Bevy's example scene ``IrradianceVolumeExample.glb`` ships such a
node, named ``IrradianceVolume``, scaled and placed over its floor. This module reads that
convention from the glTF JSON:

* :func:`node_volume` -- the box of the node named ``NAME`` (``--volume-node``): the eight
  corners of ``[-0.5, 0.5]^3`` through the node's world matrix (its parents' transforms
  included, glTF's column-vector 4x4), and the **axis-aligned bounds of those corners**. A node
  that is rotated (its world matrix's 3x3 part not diagonal up to 1e-6 of its scale) keeps its
  axis-aligned bounds, a box larger than the rotated cube, and :attr:`ProbeVolume.rotated` says
  so (the bake prints it): probe grids here are axis-aligned.
* :func:`find_volume_node` -- the node a scene names like a probe volume, when no option
  chooses: a name that, lower-cased with everything but letters and digits dropped, contains
  ``irradiancevolume``, ``lightprobe`` or ``probevolume`` (:data:`VOLUME_WORDS`). Exactly one
  such node is used; several are refused with their names (``--volume-node`` chooses one).

Only nodes of the default scene (``scene``, else the first) count: the others have no world
transform. References: glTF 2.0 specification, "Transformations"; Bevy 0.14
``bevy_pbr::light_probe`` ("the light probe's influence is a 1x1x1 cube centered at the
origin, transformed by the entity's transform").
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np
from numpy.typing import NDArray

from probegrid.scene.gltf import _GLB_MAGIC, _node_world_matrices, _parse_glb
from probegrid.scene.model import SceneError

__all__ = ["VOLUME_WORDS", "ProbeVolume", "find_volume_node", "node_volume"]

#: What a node's name contains (lower-cased, letters and digits only) to mark a probe volume.
VOLUME_WORDS: Final[tuple[str, ...]] = ("irradiancevolume", "lightprobe", "probevolume")

#: The unit cube's corners, ``(8, 3)``: Bevy's light-probe volume before its transform.
_CORNERS: Final[NDArray[np.float64]] = np.array(
    [[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])


@dataclass(frozen=True)
class ProbeVolume:
    """A node's probe volume: its name, glTF index, world matrix and axis-aligned box."""

    name: str
    index: int
    matrix: NDArray[np.float64]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    rotated: bool

    def describe(self) -> str:
        """One line: which node, the convention, the box."""
        box = ",".join(f"{v:.4g}" for v in (*self.lo, *self.hi))
        text = (f"probe volume from node {self.name!r} (the unit cube -0.5..0.5 by its world "
                f"transform): bounds {box}")
        if self.rotated:
            text += " (the node is rotated: the grid covers its box's axis-aligned bounds)"
        return text


def _document(path: Path) -> dict:
    """The glTF JSON of a ``.gltf`` or ``.glb`` file (a ``.glb``'s JSON chunk only: no
    buffer or image is read)."""
    try:
        with open(path, "rb") as f:
            data = f.read(20)
            if data[:4] == _GLB_MAGIC and len(data) == 20:
                length = int.from_bytes(data[12:16], "little")
                data += f.read(length)  # (the first chunk, JSON; checked by _parse_glb)
                head = bytearray(data)
                head[8:12] = len(data).to_bytes(4, "little")  # the container's length: to here
                return _parse_glb(bytes(head), path.name)[0]
            data += f.read()
    except OSError as exc:
        raise SceneError(f"cannot read {path}: {exc.strerror or exc}") from None
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneError(f"{path.name} is not valid glTF JSON ({exc}).") from None
    if not isinstance(doc, dict):
        raise SceneError(f"{path.name} is not a glTF JSON object.")
    return doc


def _named(doc: dict, path: Path) -> list[tuple[int, str, NDArray[np.float64]]]:
    """(index, name, world matrix) of every node of the default scene, in index order."""
    world = _node_world_matrices(doc, path.name)
    nodes = doc.get("nodes", [])
    return [(i, str(nodes[i].get("name", "")), world[i]) for i in sorted(world)]


def _volume(index: int, name: str, m: NDArray[np.float64]) -> ProbeVolume:
    corners = _CORNERS @ m[:3, :3].T + m[:3, 3]
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    if not np.all(hi > lo):
        raise SceneError(f"node {name!r} has a flat or degenerate transform (scale "
                         f"{np.round(hi - lo, 6).tolist()}): no volume to fill with probes")
    a = m[:3, :3]
    rotated = bool(np.max(np.abs(a - np.diag(np.diag(a)))) > 1e-6 * np.max(np.abs(a)))
    return ProbeVolume(name, index, m, lo, hi, rotated)


def node_volume(path: str | Path, name: str) -> ProbeVolume:
    """The probe volume of the node named ``name`` (exactly, case first, then ignoring case)
    in the default scene of the glTF file ``path``; :class:`SceneError` naming the nodes there
    are when none or several match."""
    p = Path(path)
    nodes = _named(_document(p), p)
    hits = [n for n in nodes if n[1] == name] or [n for n in nodes if n[1].lower() == name.lower()]
    if len(hits) == 1:
        return _volume(*hits[0])
    if hits:
        raise SceneError(f"--volume-node: {len(hits)} nodes of {p.name} are named {name!r} "
                         f"(nodes {', '.join(str(h[0]) for h in hits)}); rename one")
    names = [n[1] for n in nodes if n[1]]
    listed = ", ".join(repr(n) for n in names[:12]) + (" ..." if len(names) > 12 else "")
    raise SceneError(f"--volume-node: no node named {name!r} in the default scene of {p.name} "
                     f"(named nodes: {listed or 'none'})")


def _is_volume_name(name: str) -> bool:
    key = re.sub(r"[^a-z0-9]", "", name.lower())
    return any(word in key for word in VOLUME_WORDS)


def find_volume_node(path: str | Path) -> ProbeVolume | None:
    """The probe volume of the one node of ``path``'s default scene named like a probe volume
    (module docstring), None when there is none; several are a :class:`SceneError` that names
    them and asks for ``--volume-node``."""
    p = Path(path)
    hits = [n for n in _named(_document(p), p) if _is_volume_name(n[1])]
    if not hits:
        return None
    if len(hits) > 1:
        raise SceneError(f"{p.name} has {len(hits)} nodes named like a probe volume ("
                         + ", ".join(repr(h[1]) for h in hits[:12])
                         + "); choose one with --volume-node NAME, or give --bounds")
    return _volume(*hits[0])
