"""The store-backed probe field: weights at points, blended SH and maps, and split-sum shading.

:class:`ProbeField` wraps an open grid store (:mod:`probegrid.store`) and answers every question
about a point with the DDGI weights and blends of :mod:`probegrid.core.ddgi`; only the probes a
query needs are read from the memory maps. The service and the Python API query through it.

Visibility
----------
A store baked with the scene's triangles (extras ``scene_vertices``/``scene_triangles``, format
2) is queried leak-free: an Embree BVH over them is built once when the field is opened, and the
segment from the query point (moved off the surface along the normal when one is given) to each
surrounding probe is cast through it (:meth:`probegrid.raytrace.RayTracer.segments_occluded`); a
probe on the far side of a wall gets weight 0 (:attr:`ProbeWeights.visibility` ``"segments"``).
Older stores fall back to what they support: DDGI's Chebyshev test on the distance moments with
a normal (``"moments"``), nothing without (``"none"``).

Maps at a point
---------------
:meth:`ProbeField.cube_at` answers ``method="trace"`` (the default) with what a probe baked at
the point would hold: a probe traced there with the bake's own estimator against the store's
converged grid (:class:`probegrid.bake.point.PointTracer`; the store keeps the scene file, the
grid its final pass read and the environment). A blend of 8 probes' maps overlays 8 views from
8 places (a mirror level shows a small light up to 8 times); the traced probe sees each thing
once, in the right direction. ``method="blend"`` keeps the blend, and a store that cannot be
traced (:meth:`ProbeField.trace_support` says why) is answered with it. The tracer (scene,
emitter and environment tables; the BVH is the field's) is built on first use, and the maps of
the last :data:`TRACE_CACHE` traced points are kept (a client fetching a chain asks once per
level).

SH at points: the SH field
--------------------------
A store baked with an SH field (:mod:`probegrid.bake.shfield`: radiance SH traced on a lattice
about twice as fine as the probes' whose outer layers sit just inside the walls) answers
:meth:`ProbeField.sh_at` from it: trilinear weights on that lattice with the same exact segment
visibility and quarter-cell extrapolation as the probes' (:meth:`ProbeField.sh_weights`), and in
the cells next to the walls the first-order term of the field's limited gradients
(:mod:`probegrid.core.fieldgradient`). ``source="probes"`` (and a store without the field)
blends the probes' SH instead.

The segments of a point inside a cell (or the block of cells around it) that no triangle
touches are not cast: it sees every corner (:meth:`ProbeField.clear_cells`,
:mod:`probegrid.core.clearcells`; found once per lattice, the weights unchanged).

SH without ringing
------------------
:meth:`ProbeField.sh` blends the *deringed* radiance SH by default (each probe windowed so that
its irradiance is non-negative over the sphere, :mod:`probegrid.core.sh.dering`; a blend with
non-negative weights of such probes stays non-negative) and the raw projection on request. A
store without the ``sh_deringed`` extra (format 1) is deringed here, once, on first use.
"""

from __future__ import annotations

import re
import threading
from collections import OrderedDict
from concurrent.futures import Future
from functools import cached_property, partial
from typing import TYPE_CHECKING, Any, Final, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import MapKind, MapMethod, SHKind, SHSource, choices
from probegrid.core.clearcells import ClearCells, clear_cells
from probegrid.core.cubemap import CubeMap
from probegrid.core.fieldgradient import (
    first_order_term,
    gradient_table,
    limited_gradients,
    outer_cells,
)
from probegrid.core.ddgi import (
    DEFAULT_NORMAL_BIAS,
    MAP_KINDS,
    QUERY_EXTRAPOLATION,
    QUERY_FACING,
    Occlusion,
    ProbeWeights,
    _points,
    blend,
    blend_lookup,
    probe_weights,
)
from probegrid.core.sh.dering import dering
from probegrid.core.grid import GridSpec
from probegrid.core.lobes import roughness_to_lod
from probegrid.core.shading import reflect, shade_split_sum
from probegrid.raytrace import RayTracer
from probegrid.store import ProbeStore

if TYPE_CHECKING:
    from probegrid.bake.point import PointMaps, PointSettings, PointTracer
    from probegrid.scene import Scene

__all__ = ['FIELD_GRADIENT', 'MAP_METHODS', 'SH_KINDS', 'SH_SOURCES', 'TRACE_CACHE', 'MapMethod', 'ProbeField',
           'SHKind', 'SHSource']

#: How :meth:`ProbeField.cube_at` makes a map: traced at the point (default) or blended.
MAP_METHODS: Final[tuple[str, ...]] = choices(MapMethod)

#: Traced points whose maps a field keeps.
TRACE_CACHE: Final = 16

#: Which SH :meth:`ProbeField.sh` blends: the deringed coefficients (default) or the raw ones.
SH_KINDS: Final[tuple[str, ...]] = choices(SHKind)

#: What :meth:`ProbeField.sh_at` interpolates: the SH field (default, where stored) or the probes.
SH_SOURCES: Final[tuple[str, ...]] = choices(SHSource)

#: Whether :meth:`ProbeField.sh_at` adds the SH field's first-order term in the cells next to
#: the walls by default (measured in docs/benchmarks.md, "The gradient term near the walls").
FIELD_GRADIENT: Final = True

#: Length left out at both ends of a visibility segment, in units of the smallest cell size
#: (a point on a surface or a probe does not hide itself; far below any wall thickness).
SEGMENT_MARGIN: Final = 1e-4


_SPECULAR_RE = re.compile(r"^specular_(\d+)$")


# ------------------------------------------------------------------------------ stores
class ProbeField:
    """Interpolation over one grid store: weights at points, blended SH and maps, shading.

    Parameters
    ----------
    store : ProbeStore
        An open store (its arrays stay memory-mapped; only the probes a query needs are read).
    normal_bias : float
        See :func:`probe_weights`.
    scene : Scene, optional
        The scene the store was baked from, for stores that keep no scene file (or to trace
        the scene as the bake saw it when that differs from the file); default: the store's.
    point_settings : PointSettings, optional
        How traced maps are made when a call names no ``quality`` (default: the ``accurate``
        preset, :data:`probegrid.bake.point.POINT_PRESETS`).

    Attributes
    ----------
    grid : GridSpec
    kinds : tuple of str
        Map kinds the store answers, among ``"diffuse"``, ``"specular"``, ``"incoming"``
        (incoming: stored, or traced at points for a store that can be traced).
    specular_levels : int
        Levels of the specular chain (0 if none).
    tracer : RayTracer or None
        Embree BVH of the store's scene triangles (built at construction), None for a store
        without them; with it every query's weights take the exact segment test.
    """

    def __init__(self, store: ProbeStore, *, normal_bias: float = DEFAULT_NORMAL_BIAS,
                 scene: Scene | None = None, point_settings: PointSettings | None = None
                 ) -> None:
        if not (np.isfinite(normal_bias) and normal_bias >= 0):
            raise ValueError(f"normal_bias must be finite and >= 0, got {normal_bias!r}.")
        self.store = store
        self.grid: GridSpec = store.grid
        self.normal_bias = float(normal_bias)
        names = set(store.names)
        spec = sorted(int(m.group(1)) for s in names if (m := _SPECULAR_RE.match(s)))
        if spec != list(range(len(spec))):
            raise ValueError(
                f"store {store.path.name} has specular levels {spec}; they must be 0..L-1."
            )
        self._specular = [f"specular_{k}" for k in spec]
        self.specular_levels = len(spec)
        self._scene = scene
        #: Whether the incoming cubes are answered by the trace only (not stored).
        self._traced_incoming = "incoming" not in names and self.trace_support() is None
        self.kinds: tuple[MapKind, ...] = tuple(
            cast(MapKind, k) for k in MAP_KINDS
            if (k == "specular" and spec) or (k != "specular" and k in names)
            or (k == "incoming" and self._traced_incoming)
        )
        extras = set(store.manifest.extras)
        #: The BVH of the scene's triangles (None for a store without them).
        self.tracer: RayTracer | None = None
        self._occluded: Occlusion | None = None
        if {"scene_vertices", "scene_triangles"} <= extras:
            self.tracer = RayTracer(store.arrays["scene_vertices"],
                                    store.arrays["scene_triangles"])
            margin = SEGMENT_MARGIN * self.grid.smallest_cell(default=1.0)
            self._occluded = partial(self.tracer.segments_occluded, margin=margin)
        self._clear: dict[str, ClearCells] = {}
        self._gradients: dict[str, NDArray[np.float64]] = {}
        self._clear_lock = threading.Lock()
        self._stored_deringed = "sh_deringed" in extras and "sh" in names
        if self._stored_deringed:
            store.arrays["sh_deringed"]  # mapped now, with the other arrays
        self._dering_lock = threading.Lock()
        self._point_settings = point_settings
        self._point_tracers: dict[str | None, PointTracer] = {}
        self._scene_tracer: RayTracer | None = None  # (a scene with cut-outs or glass)
        self._trace_lock = threading.Lock()
        self._traced: OrderedDict[bytes, PointMaps] = OrderedDict()
        self._tracing: dict[bytes, Future[PointMaps]] = {}

    def __repr__(self) -> str:
        return f"ProbeField({self.store!r}, kinds={self.kinds})"

    def _array(self, name: str) -> NDArray[Any] | None:
        return self.store.arrays[name] if name in self.store.manifest.arrays else None

    @cached_property
    def _visibility(self) -> tuple[NDArray[np.bool_] | None, NDArray[Any] | None,
                                   NDArray[Any] | None]:
        """``valid`` (in memory: P bytes), ``positions`` and ``moments`` (maps), mapped once."""
        valid = self._array("valid")
        return (None if valid is None else np.array(valid, dtype=bool),
                self._array("positions"), self._array("moments"))

    def map_levels(self, kind: MapKind) -> int:
        """Number of levels of a map kind (1 for diffuse and incoming)."""
        self._check_kind(kind)
        return self.specular_levels if kind == "specular" else 1

    def map_size(self, kind: MapKind, level: int = 0) -> int:
        """Face size of a map kind's level."""
        if kind == "incoming" and self._traced_incoming:
            self._check_kind(kind)
            if level != 0:
                raise ValueError(f"level must be an integer in 0..0 for incoming maps, got "
                                 f"{level!r}.")
            return int(self.store.manifest.bake["settings"]["face_size"])
        return int(self._level(kind, level).shape[2])

    def _check_kind(self, kind: str) -> None:
        if kind not in self.kinds:
            raise ValueError(
                f"this store has no {kind!r} maps; it has {', '.join(map(repr, self.kinds))}."
            )

    def _level(self, kind: MapKind, level: int) -> NDArray[Any]:
        levels = self.map_levels(kind)
        if not isinstance(level, (int, np.integer)) or isinstance(level, bool) or not (
            0 <= level < levels
        ):
            raise ValueError(
                f"level must be an integer in 0..{levels - 1} for {kind} maps, got {level!r}."
            )
        name = self._specular[level] if kind == "specular" else kind
        return self.store.arrays[name]

    def visibility_test(self, *, normal: bool) -> str:
        """The visibility test :meth:`weights` applies with or without normals: ``"segments"``
        (exact, the store keeps the scene's triangles), ``"moments"`` (a normal and stored
        distance moments) or ``"none"``."""
        if self._occluded is not None:
            return "segments"
        return "moments" if normal and self._visibility[2] is not None else "none"

    def weights(self, points: ArrayLike, *, normals: ArrayLike | None = None,
                extrapolate: bool = True) -> ProbeWeights:
        """:func:`probe_weights` with the store's validity, probe positions and moments, and
        the exact segment test when the store keeps the scene's triangles (module docstring);
        the result's ``visibility`` says which test was used. A normal enters the visibility
        test only, not the weights, and with ``extrapolate`` a point up to a quarter cell
        outside the probes' box is extrapolated linearly (the SH's weights); without it, it is
        clamped onto the box (the maps' weights: extrapolating a cube that holds a small
        bright light magnifies the probes' disagreement about where it is). See section
        "Queries" of :mod:`probegrid.core.ddgi`."""
        valid, positions, moments = self._visibility
        return probe_weights(
            self.grid,
            points,
            valid=valid,
            normals=normals,
            probe_positions=positions,
            moments=moments,
            normal_bias=self.normal_bias,
            occluded=self._occluded,
            extrapolate=QUERY_EXTRAPOLATION if extrapolate else 0.0,
            facing=QUERY_FACING,
            clear=self.clear_cells("probes"),
        )

    @cached_property
    def _computed_deringed(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(sh (P, 9, 3), window (P, 3))`` deringed here (stores without the extras)."""
        deringed, window, _ = dering(np.asarray(self.store.arrays["sh"], dtype=np.float64))
        return deringed, window

    @staticmethod
    def _check_sh_kind(kind: str) -> None:
        if kind not in SH_KINDS:
            raise ValueError(f"sh kind must be one of {', '.join(SH_KINDS)}, got {kind!r}.")

    def sh_array(self, kind: SHKind = "deringed") -> NDArray[Any]:
        """The per-probe ``(P, 9, 3)`` coefficients of ``kind`` (a memory map when stored)."""
        self._check_sh_kind(kind)
        if kind == "raw":
            return self.store.arrays["sh"]
        if self._stored_deringed:
            return self.store.arrays["sh_deringed"]
        with self._dering_lock:
            return self._computed_deringed[0]

    def sh_window(self) -> NDArray[Any]:
        """``(P, 3)`` band factors ``(1, h_1, h_2)`` of each probe's deringing window."""
        if self._stored_deringed and "sh_window" in self.store.manifest.extras:
            return self.store.arrays["sh_window"]
        with self._dering_lock:
            return self._computed_deringed[1]

    def sh(self, weights: ProbeWeights, *, kind: SHKind = "deringed") -> NDArray[np.float64]:
        """``(n, 9, 3)`` float64 blended SH radiance coefficients: deringed (each probe's
        irradiance non-negative everywhere, the default) or ``kind="raw"``."""
        return blend(self.sh_array(kind), weights)

    # -- the SH field -------------------------------------------------------------------------
    @cached_property
    def sh_field(self) -> tuple[GridSpec, NDArray[np.bool_], NDArray[np.float32]] | None:
        """The store's SH field lattice, its points' validity and positions (None: the store
        has none)."""
        from probegrid.bake.shfield import SH_FIELD_EXTRAS, lattice_from_extra

        if not set(SH_FIELD_EXTRAS) <= set(self.store.manifest.extras):
            return None
        lattice = lattice_from_extra(self.store.arrays["sh_field_lattice"])
        # (float32 positions, as a store's: the weights' compiled kernels take those)
        return (lattice, np.array(self.store.arrays["sh_field_valid"], dtype=bool),
                np.ascontiguousarray(lattice.positions(), dtype=np.float32))

    @cached_property
    def _sh_field_bias(self) -> float:
        """The normal bias on the SH field's lattice: the probes' offset, in its cells."""
        assert self.sh_field is not None
        return self.normal_bias * (self.grid.smallest_cell(default=1.0)
                                   / self.sh_field[0].smallest_cell(default=1.0))

    def clear_cells(self, lattice: SHSource) -> ClearCells | None:
        """The cells of the probes' grid (``"probes"``) or the SH field's lattice
        (``"field"``) whose box no triangle of the store's scene touches
        (:mod:`probegrid.core.clearcells`; None without the scene's triangles or that
        lattice): a query point inside one casts no visibility segment. Found on first use
        (a few milliseconds for thousands of cells and triangles) and kept."""
        if self.tracer is None or (lattice == "field" and self.sh_field is None):
            return None
        got = self._clear.get(lattice)
        if got is None:
            with self._clear_lock:
                got = self._clear.get(lattice)
                if got is None:
                    if lattice == "field":
                        assert self.sh_field is not None
                        grid, positions = self.sh_field[0], self.sh_field[2]
                    else:
                        grid, positions = self.grid, self._visibility[1]
                    got = self._clear[lattice] = clear_cells(
                        grid, self.store.arrays["scene_vertices"],
                        self.store.arrays["scene_triangles"], positions=positions)
        return got

    def sh_source(self, kind: SHKind = "deringed") -> str:
        """Where :meth:`sh` takes the ``kind`` coefficients from: ``"store"`` or, for deringed
        SH of a store without them, ``"computed"`` (deringed on first use)."""
        self._check_sh_kind(kind)
        return "store" if kind == "raw" or self._stored_deringed else "computed"

    def sh_weights(self, points: ArrayLike, *, normals: ArrayLike | None = None,
                   source: SHSource = "field") -> tuple[ProbeWeights, SHSource]:
        """The weights :meth:`sh_at` blends with and what they index: the SH field's lattice
        points (``"field"``, where the store has one) or the probes (:meth:`weights`). On the
        field: trilinear weights of its valid points, each tested with the exact segments when
        the store keeps the scene (the normal moves the segments' start off the surface by the
        same length as for the probes), extrapolated linearly up to a quarter lattice step
        outside its box."""
        if source not in SH_SOURCES:
            raise ValueError(f"source must be one of {', '.join(SH_SOURCES)}, got {source!r}.")
        if source == "probes" or self.sh_field is None:
            return self.weights(points, normals=normals), "probes"
        lattice, valid, positions = self.sh_field
        return probe_weights(lattice, points, valid=valid, normals=normals,
                             probe_positions=positions, normal_bias=self._sh_field_bias,
                             occluded=self._occluded,
                             extrapolate=QUERY_EXTRAPOLATION, facing=False,
                             clear=self.clear_cells("field")), "field"

    def sh_at(self, points: ArrayLike, *, normals: ArrayLike | None = None,
              kind: SHKind = "deringed", source: SHSource = "field",
              gradient: bool | None = None
              ) -> tuple[NDArray[np.float64], ProbeWeights, SHSource]:
        """``(n, 9, 3)`` float64 radiance SH at points, the weights used and what they index
        (:meth:`sh_weights`): interpolated on the SH field where the store has one (deringed
        at each lattice point, or ``kind="raw"``), else blended from the probes (:meth:`sh`).
        On the field, a point in a cell next to the walls (and one extrapolated beyond them)
        adds the first-order term of the field's limited gradients
        (:mod:`probegrid.core.fieldgradient`; ``gradient=False``: the plain interpolation;
        None: :data:`FIELD_GRADIENT`)."""
        self._check_sh_kind(kind)
        if gradient is None:
            gradient = FIELD_GRADIENT
        w, used = self.sh_weights(points, normals=normals, source=source)
        if used == "probes":
            return self.sh(w, kind=kind), w, used
        name = "sh_field" if kind == "deringed" else "sh_field_raw"
        coefficients = blend(self.store.arrays[name], w)
        if gradient:
            if len(w) == 1:  # (one point: Python's flags, no array of rows)
                if self._field_outer[1][int(w.indices[0, 0])] and not w.unlit[0]:
                    coefficients += first_order_term(
                        self._gradient_table(kind), w.indices, w.weights,
                        w.points).reshape(coefficients.shape)
            else:
                rows = np.flatnonzero(self._field_outer[0][w.indices[:, 0]] & ~w.unlit)
                if rows.size:
                    coefficients[rows] += first_order_term(
                        self._gradient_table(kind), w.indices[rows], w.weights[rows],
                        w.points[rows]).reshape(-1, *coefficients.shape[1:])
        return coefficients, w, used

    @cached_property
    def _field_outer(self) -> tuple[NDArray[np.bool_], list[bool]]:
        """Per SH field lattice point, whether its cell is one next to the walls
        (:func:`probegrid.core.fieldgradient.outer_cells`), as an array and a list."""
        assert self.sh_field is not None
        outer = outer_cells(self.sh_field[0])
        return outer, outer.tolist()

    def _gradient_table(self, kind: SHKind) -> NDArray[np.float64]:
        """:func:`probegrid.core.fieldgradient.gradient_table` of :meth:`field_gradients`."""
        got = self._gradients.get(f"table {kind}")
        if got is None:
            assert self.sh_field is not None
            table = gradient_table(self.field_gradients(kind), self.sh_field[2])
            with self._clear_lock:
                got = self._gradients.setdefault(f"table {kind}", table)
        return got

    def field_gradients(self, kind: SHKind = "deringed") -> NDArray[np.float64]:
        """``(M, 9, 3, 3)`` limited gradients of the SH field's ``kind`` coefficients
        (:func:`probegrid.core.fieldgradient.limited_gradients`), found on first use and
        kept."""
        self._check_sh_kind(kind)
        if self.sh_field is None:
            raise ValueError("this store has no SH field.")
        got = self._gradients.get(kind)
        if got is None:
            with self._clear_lock:
                got = self._gradients.get(kind)
                if got is None:
                    lattice, valid, _ = self.sh_field
                    name = "sh_field" if kind == "deringed" else "sh_field_raw"
                    got = self._gradients[kind] = limited_gradients(
                        self.store.arrays[name], lattice, valid=valid)
        return got

    def cube(self, weights: ProbeWeights, kind: MapKind, *, level: int = 0) -> NDArray[np.float32]:
        """``(n, 6, s, s, 3)`` float32 blended cube of one map kind and level."""
        return blend(self._level(kind, level), weights, dtype=np.float32)

    def cubemap(self, weights: ProbeWeights, kind: MapKind) -> list[CubeMap]:
        """Blended maps of every point as :class:`CubeMap` s (all levels for specular)."""
        levels = [self.cube(weights, kind, level=k) for k in range(self.map_levels(kind))]
        return [CubeMap(tuple(lv[i] for lv in levels), kind=kind) for i in range(len(weights))]

    # -- maps traced at points ----------------------------------------------------------------
    def trace_support(self) -> str | None:
        """Why this store's maps cannot be traced at points (None: they can)."""
        from probegrid.bake.point import trace_support

        has_scene = self._scene is not None or self.store.manifest.scene_file is not None
        return trace_support(self.store.manifest, set(self.store.manifest.extras), has_scene)

    def map_method(self, method: MapMethod = "trace") -> MapMethod:
        """The method :meth:`cube_at` uses when asked for ``method``: ``"trace"`` falls back
        to ``"blend"`` for a store that cannot be traced (:meth:`trace_support`)."""
        if method not in MAP_METHODS:
            raise ValueError(f"method must be one of {', '.join(MAP_METHODS)}, got {method!r}.")
        return "trace" if method == "trace" and self.trace_support() is None else "blend"

    def point_tracer(self, quality: str | None = None) -> PointTracer:
        """The store's :class:`probegrid.bake.point.PointTracer` of a preset ``quality``
        (:data:`probegrid.bake.point.POINT_PRESETS`; None: the field's ``point_settings``),
        built on first use and kept (one per preset: the BVH is shared)."""
        from probegrid.bake.point import PointSettings, PointTracer

        ps = self._point_settings if quality is None else PointSettings.preset(quality)
        with self._trace_lock:
            if quality not in self._point_tracers:
                if self._scene is None:  # (read once, for every preset)
                    from probegrid.scene import load_gltf

                    kept = self.store.manifest.scene_file
                    assert kept is not None
                    # (the bake had to ignore every extension it refused: the same scene)
                    self._scene = load_gltf(self.store.path / kept.file,
                                            ignore_extensions=("*",))
                scene = self._scene
                # the visibility tracer knows the triangles only; a scene with cut-outs or
                # glass traces with its own (what a ray passes), built once for every preset
                tracer = self.tracer
                if scene.coverage is not None:
                    if self._scene_tracer is None:
                        self._scene_tracer = RayTracer.from_scene(scene)
                    tracer = self._scene_tracer
                self._point_tracers[quality] = PointTracer.from_store(
                    self.store, scene, tracer=tracer, settings=ps)
            return self._point_tracers[quality]

    def point_maps(self, point: ArrayLike, *, quality: str | None = None) -> PointMaps:
        """What a probe traced at ``point (3,)`` holds (its incoming cube, diffuse map and GGX
        chain), traced with preset ``quality`` (:meth:`point_tracer`); the last
        :data:`TRACE_CACHE` answers are kept. Points are traced side by side on the service's
        threads; concurrent requests for one point (a client fetching every level at once)
        wait for its one trace."""
        p = _points(point, "point")
        if len(p) != 1:
            raise ValueError("point_maps traces one point.")
        tracer = self.point_tracer(quality)
        key = np.ascontiguousarray(p[0], dtype="<f8").tobytes() + (quality or "").encode()
        with self._trace_lock:
            got = self._traced.get(key)
            if got is not None:
                self._traced.move_to_end(key)
                return got
            pending = self._tracing.get(key)
            if pending is None:
                pending = self._tracing[key] = Future()
                mine = True
            else:
                mine = False
        if not mine:
            return cast("PointMaps", pending.result())
        try:
            got = tracer.maps(p[0])
        except BaseException as exc:
            with self._trace_lock:
                del self._tracing[key]
            pending.set_exception(exc)
            raise
        with self._trace_lock:
            del self._tracing[key]
            self._traced[key] = got
            while len(self._traced) > TRACE_CACHE:
                self._traced.popitem(last=False)
        pending.set_result(got)
        return got

    def cube_at(self, point: ArrayLike, kind: MapKind, *, level: int = 0,
                method: MapMethod = "trace", normal: ArrayLike | None = None,
                quality: str | None = None
                ) -> tuple[NDArray[np.float32], ProbeWeights, MapMethod]:
        """One map level ``(6, s, s, 3)`` float32 at one point, the blend's weights (for the
        flags; the traced map does not use them) and the method used (:meth:`map_method`; the
        blend too for a point inside a solid, whose traced rays meet back faces more often than
        the bake lets a probe's). ``quality``: the traced answer's preset
        (:meth:`point_tracer`). Incoming cubes a store does not keep are traced only."""
        self.map_size(kind, level)  # checks kind and level
        if quality is not None:
            from probegrid.bake.point import PointSettings

            PointSettings.preset(quality)  # checked before any work
        used = self.map_method(method)
        traced_only = kind == "incoming" and self._traced_incoming
        if traced_only and used == "blend":
            raise ValueError("this store keeps no incoming maps to blend; they are traced "
                             "(method=trace).")
        w = self.weights(point, normals=normal, extrapolate=False)
        if used == "blend":
            return self.cube(w, kind, level=level)[0], w, used
        maps = self.point_maps(point, quality=quality)
        limit = float(self.store.manifest.bake["settings"].get("invalid_threshold", 0.25))
        if maps.backface_fraction > limit and not traced_only:
            return self.cube(w, kind, level=level)[0], w, "blend"
        faces = (maps.incoming if kind == "incoming" else maps.diffuse if kind == "diffuse"
                 else maps.specular[level])
        return faces, w, used

    def shade(
        self,
        points: ArrayLike,
        normals: ArrayLike,
        views: ArrayLike,
        *,
        albedo: ArrayLike,
        roughness: ArrayLike,
        f0: ArrayLike,
        dfg: ArrayLike,
    ) -> tuple[NDArray[np.float32], ProbeWeights]:
        """Split-sum shading of surface points with the blended probe maps.

        ``out = kd Diffuse[N] + ks Prefiltered[R, roughness (L - 1)]`` with ``kd = albedo (1 - s)``,
        ``ks = s = F0 A + B`` exactly as :func:`probegrid.core.shading.shade_split_sum` (whose
        formula is used: the two factors are obtained by shading unit maps), and the lookups of
        the blended maps done per probe (:func:`blend_lookup`). The weights use the normals
        (DDGI visibility).

        Parameters
        ----------
        points, normals, views : (n, 3) float
            Positions, normals and surface-to-eye vectors (any non-zero length).
        albedo, f0 : (n, 3) or (3,) float
        roughness : (n,) or scalar float in [0, 1]
        dfg : (S, S, 2) float
            :func:`probegrid.core.dfg.dfg_lut`.

        Returns
        -------
        rgb : (n, 3) float32
        weights : ProbeWeights
        """
        if "diffuse" not in self.kinds or "specular" not in self.kinds:
            raise ValueError("shading needs a store with diffuse and specular maps.")
        p = _points(points, "points")
        nrm = _points(normals, "normals")
        v = _points(views, "views")
        if not nrm.shape[0] == v.shape[0] == p.shape[0]:
            raise ValueError("points, normals and views must have the same number of rows.")
        w = self.weights(p, normals=nrm, extrapolate=False)
        alb = np.broadcast_to(np.asarray(albedo, dtype=np.float64), p.shape)
        spec_f0 = np.broadcast_to(np.asarray(f0, dtype=np.float64), p.shape)
        r = np.broadcast_to(np.asarray(roughness, dtype=np.float64), p.shape[:1])
        # shade_split_sum is linear in its two lookups: with unit maps in channels 0-2 (diffuse)
        # and 3-5 (specular) it returns the factors kd and ks of each lookup.
        unit_d = np.zeros((6, 1, 1, 6), np.float32)
        unit_d[..., :3] = 1.0
        factors = shade_split_sum(
            nrm, v,
            albedo=np.concatenate([alb, alb], axis=-1),
            roughness=r,
            f0=np.concatenate([spec_f0, spec_f0], axis=-1),
            diffuse=unit_d,
            specular_levels=[1.0 - unit_d],
            dfg=dfg,
        ).astype(np.float64)
        diffuse = blend_lookup([self.store.arrays["diffuse"]], w, nrm)
        levels = [self.store.arrays[name] for name in self._specular]
        lod = roughness_to_lod(r, len(levels))
        prefiltered = blend_lookup(levels, w, reflect(v, nrm), lod=lod)
        rgb = factors[:, :3] * diffuse + factors[:, 3:] * prefiltered
        return rgb.astype(np.float32), w

