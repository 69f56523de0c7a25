"""Real grid stores for the interpolation, service and client tests (written with StoreWriter).

The probes of :func:`linear_store` hold values that are *affine functions of the probe position*
(small integers and quarters, exact in float32), so any blend with trilinear weights must
reproduce :func:`linear_values` at any point inside a cell exactly, and a map served over HTTP
can be checked against the library to the last bit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from probegrid.core.conventions import conventions
from probegrid.core.cubemap import mip_sizes
from probegrid.core.grid import GridSpec
from probegrid.store import ArraySpec, ProbeStore, StoreWriter

#: Grid of the standard test store: 3 x 2 x 3 probes, spacing 1.
GRID = GridSpec.from_counts((0.0, 0.0, 0.0), (2.0, 1.0, 2.0), (3, 2, 3))


def write_store(path: Path, grid: GridSpec, arrays: dict[str, np.ndarray], *,
                scene: Path | None = None) -> ProbeStore:
    """Write ``arrays`` (each ``(P, ...)``) as a finished store at ``path`` (keeping a copy of
    the glTF ``scene`` if given) and open it."""
    specs = {
        name: ArraySpec(shape=a.shape[1:], dtype=a.dtype.str, description=f"test {name}")
        for name, a in arrays.items()
    }
    writer = StoreWriter.create(
        path,
        arrays=specs,
        grid=grid,
        conventions=conventions(),
        scene_hash="synthetic-linear",
        bake={"synthetic": True},
    )
    writer.write(np.arange(grid.n_probes), arrays)
    return writer.finish(quality={"invalid_probes": int(np.sum(~arrays["valid"]))
                                  if "valid" in arrays else 0}, scene_file=scene)


def _pattern(shape: tuple[int, ...], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Constant part (quarters in [6, 10)) and position gradient (integers in [-1, 1]) per element,
    so values are positive over the box of :data:`GRID`."""
    rng = np.random.default_rng(seed)
    const = rng.integers(24, 40, size=shape) / 4.0
    grad = rng.integers(-1, 2, size=(3, *shape)).astype(np.float64)
    return const, grad


def linear_values(name: str, shape: tuple[int, ...], points: np.ndarray) -> np.ndarray:
    """The affine field ``const + x gx + y gy + z gz`` of array ``name`` at ``points (n, 3)``
    (divided by 32 for ``incoming``, to keep it inside [0, 1] for 8-bit previews)."""
    seed = sum(map(ord, name))
    const, grad = _pattern(shape, seed)
    p = np.asarray(points, dtype=np.float64)
    scale = 1.0 / 32.0 if name == "incoming" else 1.0
    return scale * (const + np.einsum("ni,i...->n...", p, grad))


def linear_shapes(
    *, diffuse_size: int = 4, specular_size: int = 8, moments_size: int = 2,
    incoming_size: int | None = 4,
) -> dict[str, tuple[int, ...]]:
    """Per-probe shapes of the linear store's map arrays."""
    shapes = {"sh": (9, 3), "diffuse": (6, diffuse_size, diffuse_size, 3)}
    for k, n in enumerate(mip_sizes(specular_size)):
        shapes[f"specular_{k}"] = (6, n, n, 3)
    if incoming_size:
        shapes["incoming"] = (6, incoming_size, incoming_size, 3)
    shapes["moments"] = (6, moments_size, moments_size, 2)
    return shapes


def linear_arrays(grid: GridSpec = GRID, **sizes: int) -> dict[str, np.ndarray]:
    """Store arrays whose maps and SH are affine in the probe position; all probes valid and on
    the lattice; moments say every direction is open (mean 100, variance 1)."""
    pos = grid.positions()
    arrays: dict[str, np.ndarray] = {}
    for name, shape in linear_shapes(**sizes).items():
        if name == "moments":
            m = np.empty((grid.n_probes, *shape), np.float32)
            m[..., 0] = 100.0
            m[..., 1] = 100.0**2 + 1.0
            arrays[name] = m
        else:
            arrays[name] = linear_values(name, shape, pos).astype(np.float32)
    arrays["valid"] = np.ones(grid.n_probes, dtype=bool)
    arrays["positions"] = pos.astype(np.float32)
    return arrays


def linear_store(path: Path, grid: GridSpec = GRID, **sizes: int) -> ProbeStore:
    """A real store of :func:`linear_arrays` at ``path``."""
    return write_store(path, grid, linear_arrays(grid, **sizes))


#: The wall of :func:`walled_store`: the plane x = 0.5 between the probe layers x = 0 and 1.
WALL_X = 0.5


def walled_store(path: Path, grid: GridSpec = GRID) -> ProbeStore:
    """:func:`linear_arrays` with the extras a bake writes (format 2): the deringed SH and its
    windows (:func:`probegrid.core.sh.dering.dering` of the linear SH, which rings) and a scene of
    one large quad in the plane x = :data:`WALL_X`, so that the probes at x = 0 are hidden
    from points at x > 0.5 and the others from points at x < 0.5."""
    from probegrid.core.sh.dering import dering
    from probegrid.scene import quad_mesh

    arrays = linear_arrays(grid)
    specs = {name: ArraySpec(shape=a.shape[1:], dtype=a.dtype.str, description=f"test {name}")
             for name, a in arrays.items()}
    writer = StoreWriter.create(path, arrays=specs, grid=grid, conventions=conventions(),
                                scene_hash="synthetic-walled", bake={"synthetic": True})
    writer.write(np.arange(grid.n_probes), arrays)
    deringed, window, _ = dering(arrays["sh"].astype(np.float64))
    writer.add_extra("sh_deringed", deringed.astype(np.float32))
    writer.add_extra("sh_window", window.astype(np.float32))
    v, t, _ = quad_mesh((WALL_X, -5.0, -5.0), (0.0, 0.0, 10.0), (0.0, 10.0, 0.0))
    writer.add_extra("scene_vertices", v.astype(np.float32))
    writer.add_extra("scene_triangles", t.astype(np.int32))
    return writer.finish(quality={"invalid_probes": 0})
