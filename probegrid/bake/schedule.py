"""The bounce schedule: which passes a bake runs over its records, what each reads, when to stop.

After the trace (bounce 0) a bake makes the grid of level ``k = 1, 2, ...`` by one pass over
the records per level (:func:`probegrid.bake.stages.bounce_task`); a pass at level ``k`` reads
the grid of level :func:`~probegrid.bake.records.grid_level_read` ``(k, depth)``: with
``depth`` gather levels, ``k - 1 - depth`` (the grid ``step = 1 + depth`` levels down). The
final pass (:func:`probegrid.bake.stages.final_task`) at level ``L`` reads the grid of level
``L - step`` the same way, so:

* ``bounces = B``: the passes make the grids up to level ``grid_level_read(B, depth)`` (with
  gather rays, ``B - 2``), and the final pass is at level ``B``;
* ``bounces = "converge"``: the passes go on until the estimated limit of the grid's total
  energy (over valid probes) changes by less than ``tolerance`` (the rule of
  :mod:`probegrid.bake.converge`, in groups of ``period = max(step, 2)`` increments), at most
  until the final level would pass ``max_bounces``; the final pass is then at level
  ``k + step`` and reads the grid extrapolated to its limit (:meth:`BounceSchedule.limit`).

:class:`BounceSchedule` holds that state for the driver, which runs the passes, and names each
pass for the progress display (:meth:`BounceSchedule.label`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.bake.converge import Convergence, convergence
from probegrid.bake.records import grid_level_read
from probegrid.bake.settings import BakeSettings

__all__ = ["BounceSchedule"]


@dataclass
class BounceSchedule:
    """Where a bake stands in its bounces (module docstring).

    Attributes
    ----------
    converge : bool
        ``bounces = "converge"``.
    cap : int
        The final level of a fixed count, or the most a converging bake makes.
    depth : int
        Gather levels (:meth:`probegrid.bake.settings.BakeSettings.gather_levels`).
    tolerance : float
        Relative change of the estimated limit that ends a converging bake.
    passes : int
        Passes made after the trace: the grid of level ``passes`` is the latest.
    energies : list of float
        The total energy of the grid of each level made so far (``E_0 .. E_passes``).
    state : Convergence
        The convergence rule's verdict after the latest pass.
    level : int or None
        The level of the final pass, once the schedule has ended the bounce passes.
    """

    converge: bool
    cap: int
    depth: int
    tolerance: float
    passes: int = 0
    energies: list[float] = field(default_factory=list)
    state: Convergence = field(default_factory=lambda: Convergence(False, None))
    level: int | None = None

    @classmethod
    def of(cls, settings: BakeSettings) -> BounceSchedule:
        """The schedule ``settings`` ask for."""
        converge = settings.bounces == "converge"
        cap = settings.max_bounces if converge else int(settings.bounces)
        return cls(converge, cap, settings.gather_levels(), settings.tolerance)

    @property
    def step(self) -> int:
        """Levels between a pass and the grid it reads: the final pass at level ``L`` reads
        the grid of level ``L - step``."""
        return 1 + self.depth

    @property
    def period(self) -> int:
        """Increments that cycle together (:mod:`probegrid.bake.converge`)."""
        return max(self.step, 2)

    @property
    def residual(self) -> float | None:
        """The convergence rule's latest residual (None for a fixed count, or before it has
        one)."""
        return self.state.residual

    def reads(self, k: int) -> int:
        """The level of the grid a pass at level ``k`` reads (negative: none)."""
        return grid_level_read(k, self.depth)

    def next_pass(self) -> int | None:
        """The level of the next bounce pass, or None when the final pass is due (then
        :attr:`level` is its level)."""
        if self.level is not None:
            return None
        if (not self.converge and self.passes >= grid_level_read(self.cap, self.depth)) or (
                self.converge and self.passes + self.step >= self.cap):
            self.level = self.cap
            return None
        self.passes += 1
        return self.passes

    def passed(self, energy: float) -> None:
        """Record the total energy of the grid the latest pass made (the trace's first); a
        converging bake then asks the convergence rule whether to stop."""
        self.energies.append(energy)
        if self.converge and self.passes > 0:
            self.state = convergence(self.energies, self.tolerance, self.period)
            if self.state.done:
                self.level = self.passes + self.step

    @property
    def extrapolates(self) -> bool:
        """The final pass reads the grid extrapolated to its limit, not the latest grid."""
        return self.state.factor is not None and self.passes >= self.period

    def limit(self, grids: dict[int, ArrayLike]) -> NDArray[np.float32]:
        """The extrapolated limit of the grid, ``G_k + (G_k - G_{k-p}) f``
        (:mod:`probegrid.bake.converge`), from the grids of each level."""
        assert self.state.factor is not None
        k, p = self.passes, self.period
        g_k = np.asarray(grids[k], dtype=np.float64)
        limit = g_k + (g_k - np.asarray(grids[k - p], np.float64)) * self.state.factor
        return limit.astype(np.float32)

    def label(self, k: int, final: bool = False) -> str:
        """The name of the pass at level ``k`` (the trace at 0), for the progress display."""
        if not self.converge:
            return f"bounce {k} of {self.cap}" + (" (final)" if final else
                                                  " (tracing)" if k == 0 else "")
        residual = self.residual
        r = "-" if residual is None else f"{100 * residual:.2g} %"
        if final:
            return f"converged: bounce {k}, residual {r} (final)"
        return "tracing: bounce 0" if k == 0 else f"converging: bounce {k}, residual {r}"
