"""The probe volume from the scene: a node's box (Bevy's unit-cube convention), found by name,
and the refusal of a default grid that would sit inside the geometry (probegrid.scene.volume,
probegrid.bake.placement, probegrid.jobs.bake)."""

from __future__ import annotations

import base64
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from probegrid.bake.executors import InlineExecutor
from probegrid.bake.inside import inside_solid
from probegrid.bake.placement import grid_for
from probegrid.cli import EXIT_BAD_INPUT, main
from probegrid.errors import SceneError
from probegrid.raytrace import RayTracer
from probegrid.scene import load_gltf
from probegrid.scene.builders import box_mesh
from probegrid.scene.volume import find_volume_node, node_volume
from probegrid.store import open_store

FAST = ["--face-size", "8", "--diffuse-size", "4", "--bounces", "0", "--samples", "2",
        "--no-progress"]

#: The floor's quadrants (x sign, z sign) -> linear base colour.
QUADRANTS = {(-1, -1): (0.8, 0.05, 0.05), (1, -1): (0.05, 0.8, 0.05),
             (-1, 1): (0.05, 0.05, 0.8), (1, 1): (0.8, 0.8, 0.05)}


def _node(name: str, *, translation=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0),
          rotation=(0.0, 0.0, 0.0, 1.0), **extra) -> dict:
    return {"name": name, "translation": list(translation), "scale": list(scale),
            "rotation": list(rotation), **extra}


def floor_gltf(path: Path, volumes: list[dict] | None = None, *, parent: dict | None = None,
               thickness: float = 0.2) -> Path:
    """A 10 x ``thickness`` x 10 floor slab (top at y = 0) of four coloured quadrants, each a
    closed box with its own material, and the ``volumes`` nodes (no mesh) under ``parent``
    (a node of the scene's roots, when given), written as a .gltf with an embedded buffer, as
    Bevy's ``IrradianceVolumeExample.glb`` is laid out."""
    blob = b""
    doc: dict = {"asset": {"version": "2.0"}, "scene": 0, "buffers": [], "bufferViews": [],
                 "accessors": [], "meshes": [], "materials": [], "nodes": []}
    roots = []
    for q, ((sx, sz), rgb) in enumerate(QUADRANTS.items()):
        lo = (min(0, 5 * sx), -thickness, min(0, 5 * sz))
        hi = (max(0, 5 * sx), 0.0, max(0, 5 * sz))
        v, t, _ = box_mesh(lo, hi)
        pos = v.astype("<f4").tobytes()
        idx = t.astype("<u4").tobytes()
        for data, target in ((pos, 34962), (idx, 34963)):
            doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob),
                                       "byteLength": len(data), "target": target})
            blob += data
        doc["accessors"].append({"bufferView": 2 * q, "componentType": 5126,
                                 "count": len(v), "type": "VEC3",
                                 "min": v.min(0).tolist(), "max": v.max(0).tolist()})
        doc["accessors"].append({"bufferView": 2 * q + 1, "componentType": 5125,
                                 "count": t.size, "type": "SCALAR"})
        doc["materials"].append({"name": f"quadrant{q}", "pbrMetallicRoughness": {
            "baseColorFactor": [*rgb, 1.0], "metallicFactor": 0.0}})
        doc["meshes"].append({"primitives": [{"attributes": {"POSITION": 2 * q},
                                              "indices": 2 * q + 1, "material": q}]})
        doc["nodes"].append({"name": f"Floor{q}", "mesh": q})
        roots.append(q)
    children = []
    for node in volumes or []:
        children.append(len(doc["nodes"]))
        doc["nodes"].append(node)
    if parent is not None:
        doc["nodes"].append({**parent, "children": children})
        roots.append(len(doc["nodes"]) - 1)
    else:
        roots.extend(children)
    doc["buffers"].append({"byteLength": len(blob), "uri": "data:application/octet-stream;"
                           "base64," + base64.b64encode(blob).decode()})
    doc["scenes"] = [{"nodes": roots}]
    path.write_text(json.dumps(doc))
    return path


@pytest.fixture
def inline(monkeypatch):
    """Bakes run in the test's process."""
    from probegrid.bake import executors

    monkeypatch.setattr(executors, "make_executor",
                        lambda **kw: InlineExecutor(check_pickle=False))


def test_a_nodes_volume_is_the_unit_cube_through_its_world_transform(tmp_path):
    """Bevy's convention: [-0.5, 0.5]^3 by the node's world matrix, parents included; a
    rotated node gives its box's axis-aligned bounds and says so."""
    f = floor_gltf(tmp_path / "f.gltf", [
        _node("IrradianceVolume", translation=(0.0, 1.6, 0.0), scale=(8.0, 3.0, 6.0)),
        _node("Turned", scale=(2.0, 1.0, 2.0),
              rotation=(0.0, math.sin(math.pi / 8), 0.0, math.cos(math.pi / 8)))],
        parent=_node("Holder", translation=(1.0, 0.0, -0.5)))
    v = node_volume(f, "IrradianceVolume")
    np.testing.assert_allclose(v.lo, [-3.0, 0.1, -3.5], atol=1e-12)
    np.testing.assert_allclose(v.hi, [5.0, 3.1, 2.5], atol=1e-12)
    assert not v.rotated and "unit cube -0.5..0.5" in v.describe()
    t = node_volume(f, "turned")  # (a name differing in case only, when it is unique)
    r = math.sqrt(2.0)  # a 2 x 2 square turned 45 degrees about +Y: half-width sqrt(2)
    np.testing.assert_allclose(t.lo, [1.0 - r, -0.5, -0.5 - r], atol=1e-12)
    np.testing.assert_allclose(t.hi, [1.0 + r, 0.5, -0.5 + r], atol=1e-12)
    assert t.rotated and "axis-aligned bounds" in t.describe()
    # probes at the centres of the volume's cells, as an irradiance volume samples its voxels
    scene = load_gltf(f)
    g = grid_for(scene, grid="4x3x2", volume=(v.lo, v.hi))
    np.testing.assert_allclose(np.unique(g.positions()[:, 0]), [-2.0, 0.0, 2.0, 4.0])
    np.testing.assert_allclose(np.unique(g.positions()[:, 1]), [0.6, 1.6, 2.6])
    np.testing.assert_allclose(np.unique(g.positions()[:, 2]), [-2.0, 1.0])
    with pytest.raises(SceneError, match="no node named 'Nope'.*'IrradianceVolume'"):
        node_volume(f, "Nope")
    with pytest.raises(ValueError, match="either --bounds or --volume-node"):
        grid_for(scene, bounds="0,0,0,1,1,1", volume=(v.lo, v.hi))


def test_the_bake_finds_the_volume_node_by_itself_and_says_so(tmp_path, inline, capsys,
                                                             monkeypatch):
    """``probegrid bake floor.gltf --environment-color ...`` with no box option uses the one
    node named like a probe volume, says so, and its default grid fills the node's box."""
    from probegrid.bake import driver

    grids = []

    def no_bake(scene, grid, out, **kwargs):
        grids.append(grid)
        raise ValueError("stopped here")

    monkeypatch.setattr(driver, "bake", no_bake)
    f = floor_gltf(tmp_path / "floor.gltf",
                   [_node("IrradianceVolume", translation=(0.0, 1.5, 0.0), scale=(8.0, 2.0, 8.0))])
    assert main(["bake", str(f), "--out", str(tmp_path / "f.probes"), "--environment-color",
                 "1,1,1", *FAST]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "probe volume from node 'IrradianceVolume'" in err and "bounds -4,0.5,-4,4,2.5,4" in err
    assert "stopped here" in err and "inside the scene's geometry" not in err
    g = grids[0]  # longest side 8 / 8: 8 x 2 x 8 probes at the centres of 1 x 1 x 1 cells
    assert g.counts == (8, 2, 8)
    np.testing.assert_allclose([g.lo, g.hi], [[-3.5, 1.0, -3.5], [3.5, 2.0, 3.5]])


@pytest.mark.slow
def test_the_probes_a_volume_node_places_see_the_floor_under_them(tmp_path, inline, capsys):
    """Baked: each probe above a quadrant sees that quadrant's colour below it (light bounced
    off the floor under the probes the node placed)."""
    f = floor_gltf(tmp_path / "floor.gltf",
                   [_node("IrradianceVolume", translation=(0.0, 1.5, 0.0), scale=(8.0, 2.0, 8.0))])
    out = tmp_path / "floor.probes"
    assert main(["bake", str(f), "--out", str(out), "--grid", "2x1x2",
                 "--environment-color", "1,1,1", *FAST, "--bounces", "1"]) == 0
    err = capsys.readouterr().err
    assert "probe volume from node 'IrradianceVolume'" in err and "bounds -4,0.5,-4,4,2.5,4" in err
    store = open_store(out)
    pos = np.asarray(store["positions"])
    np.testing.assert_allclose(pos, [[-2, 1.5, -2], [-2, 1.5, 2], [2, 1.5, -2], [2, 1.5, 2]])
    # the probe's view of the floor: its irradiance from below (the -Y face of the diffuse map)
    below = np.asarray(store["diffuse"])[:, 3].mean(axis=(1, 2))  # (P, 3)
    for p, rgb in zip(pos, below, strict=True):
        albedo = np.array(QUADRANTS[(int(np.sign(p[0])), int(np.sign(p[2])))])
        assert int(np.argmax(rgb)) == int(np.argmax(albedo)) or albedo[0] == albedo[1]
        np.testing.assert_array_less(rgb[albedo < 0.5], rgb[albedo > 0.5].min())


def test_several_volume_nodes_are_named_and_refused_before_any_work(tmp_path, inline, capsys):
    f = floor_gltf(tmp_path / "floor.gltf", [
        _node("IrradianceVolume.001", scale=(4.0, 2.0, 4.0), translation=(2, 1, 2)),
        _node("light_probe_volume", scale=(4.0, 2.0, 4.0), translation=(-2, 1, -2)),
        _node("Lamp")])
    out = tmp_path / "floor.probes"
    assert main(["bake", str(f), "--out", str(out), "--environment-color", "1,1,1",
                 *FAST]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert ("2 nodes named like a probe volume ('IrradianceVolume.001', 'light_probe_volume')"
            in err[0] and "--volume-node NAME" in err[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["floor.gltf"]
    assert find_volume_node(floor_gltf(tmp_path / "none.gltf", [_node("Lamp")])) is None
    v = node_volume(f, "light_probe_volume")
    np.testing.assert_allclose([v.lo, v.hi], [[-4, 0, -4], [0, 2, 0]])


def test_a_default_grid_inside_a_floor_slab_is_refused_before_tracing(tmp_path, inline,
                                                                       capsys, monkeypatch):
    """The floor alone (no volume node): its default grid would be one layer inside the slab.
    Refused before any bake starts, in one line, with a box above the slab to use instead;
    that box's probes are all outside the slab. A flat scene (a slab of no thickness) too."""
    from probegrid.bake import driver

    def no_bake(*args, **kwargs):
        raise AssertionError("the bake started")

    monkeypatch.setattr(driver, "bake", no_bake)
    f = floor_gltf(tmp_path / "floor.gltf")
    out = tmp_path / "floor.probes"
    assert main(["bake", str(f), "--out", str(out), "--environment-color", "1,1,1",
                 *FAST]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "inside the scene's geometry" in err[0], err
    assert "--volume-node" in err[0]
    box = re.search(r"e\.g\. --bounds (\S+)", err[0]).group(1)
    lo, hi = np.array(box.split(","), dtype=float).reshape(2, 3)
    assert lo[1] > 0 and hi[1] > lo[1] + 1  # a layer above the slab's top (y = 0)
    assert np.all(lo[[0, 2]] > -5) and np.all(hi[[0, 2]] < 5)
    scene = load_gltf(f)
    p = grid_for(scene, bounds=box).positions()
    assert not inside_solid(RayTracer.from_scene(scene), scene, p).any()
    assert sorted(x.name for x in tmp_path.iterdir()) == ["floor.gltf"]  # no work files
    # a floor of no thickness: flat bounds
    b = floor_gltf(tmp_path / "flat.gltf", thickness=1e-4)
    with pytest.raises(ValueError, match=r"the scene is flat.*--bounds -4.*,0.3125,"):
        grid_for(load_gltf(b))


def test_a_binary_gltfs_volume_node_is_read_from_its_json_chunk(tmp_path):
    """The same scene as a .glb (as Bevy ships IrradianceVolumeExample.glb): the node is found
    from the JSON chunk alone."""
    from probegrid.scene.gltf import _build_glb

    f = floor_gltf(tmp_path / "f.gltf", [_node("IrradianceVolume", translation=(0, 1.5, 0),
                                               scale=(8, 2, 8))])
    doc = json.loads(f.read_text())
    blob = base64.b64decode(doc["buffers"][0].pop("uri").split(",", 1)[1])
    glb = tmp_path / "f.glb"
    glb.write_bytes(_build_glb(doc, blob))
    v = find_volume_node(glb)
    np.testing.assert_allclose([v.lo, v.hi], [[-4, 0.5, -4], [4, 2.5, 4]])
