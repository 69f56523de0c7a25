"""Progress of ``probegrid bake`` on stderr: a bar on a terminal, plain lines elsewhere.

:class:`BakeProgress` is the bake's progress callback ``(stage, Progress, rays)``:

* on a terminal, a tqdm bar per stage (probes done, time left) with the rate in Mrays/s;
* when stderr is not a terminal (a log file, ``nohup``, CI), one plain line every
  :data:`PLAIN_INTERVAL` seconds and one when a stage ends, e.g.
  ``bake: bounce 1/2: 1200/4096 probes (29 %), 3.1 Mrays/s, about 2 min left``, so a long
  bake in the background is never silent for minutes.

Rates are shown only once they mean something: after :data:`RATE_AFTER` seconds of the stage
*and* at least two updates, measured from the stage's first update (not from before its first
batch, whose work was done before the clock started: that gave figures such as
"578524 probe/s, 0.00 Mrays/s"). A machine's first bake first compiles its kernels
(:meth:`BakeProgress.compiling`: ``bake: compiling kernels (first run only, numba caches them):
12/36 kernels, 20 s so far``). :func:`resume_note` says, as a bake starts, whether it
resumes an interrupted one and from where; :func:`size_note` what the store will take with
float32 and with half-float maps.
"""

from __future__ import annotations

import os
import shutil
import sys
import time
from pathlib import Path
from typing import IO, TYPE_CHECKING

if TYPE_CHECKING:
    from probegrid.bake.executors import Progress
    from probegrid.bake.settings import BakeSettings

__all__ = ["COMPILING", "PLAIN_INTERVAL", "RATE_AFTER", "BakeProgress", "resume_note", "size_note"]

#: Seconds between two plain progress lines (stderr not a terminal).
PLAIN_INTERVAL = 10.0
#: Seconds of a stage before a rate is shown.
RATE_AFTER = 1.0
#: How the progress names the compiling of the bake's kernels (a machine's first bake).
COMPILING = "compiling kernels (first run only, numba caches them)"


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


class BakeProgress:
    """The bake's progress callback (see the module docstring).

    Parameters
    ----------
    enabled : bool
        False prints nothing (``--no-progress``).
    stream : file, optional
        Default ``sys.stderr``.
    terminal : bool, optional
        Draw a bar; default: whether ``stream`` is a terminal.
    clock : callable, optional
        Seconds (``time.monotonic``); tests pass their own.
    """

    def __init__(self, enabled: bool = True, *, stream: IO[str] | None = None,
                 terminal: bool | None = None, clock=time.monotonic) -> None:
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = (terminal if terminal is not None
                         else bool(getattr(self.stream, "isatty", lambda: False)()))
        self.clock = clock
        self._bar = None
        self._stage: str | None = None
        self._t0 = 0.0
        self._done0 = 0
        self._rays0 = 0
        self._updates = 0
        self._last_line = 0.0

    def rates(self, p: Progress, rays: int) -> tuple[float, float] | None:
        """(probes/s, Mrays/s) of the stage so far, or None while too early to tell."""
        dt = self.clock() - self._t0
        if self._updates < 2 or dt < RATE_AFTER:
            return None
        return (p.probes_done - self._done0) / dt, (rays - self._rays0) / dt / 1e6

    def __call__(self, stage: str, p: Progress, rays: int) -> None:
        if not self.enabled:
            return
        if stage != self._stage:
            self.close()
            self._stage, self._t0, self._updates = stage, self.clock(), 0
            self._done0, self._rays0 = p.probes_done, rays
            self._last_line = self._t0
        self._updates += 1
        rates = self.rates(p, rays)
        if self.terminal:
            self._draw(stage, p, rates)
            return
        now = self.clock()
        finished = p.probes_done >= p.probes_total
        if finished or now - self._last_line >= PLAIN_INTERVAL:
            self._last_line = now
            print(self.line(stage, p, rates), file=self.stream, flush=True)

    def compiling(self, done: int, total: int, *, finished: bool = False) -> None:
        """Show the compiling of the bake's kernels (a machine's first bake): ``done`` of
        ``total`` kernels in numba's cache so far; ``finished`` once the workers run."""
        if not self.enabled:
            return
        stage = COMPILING
        if stage != self._stage:
            self.close()
            self._stage, self._t0 = stage, self.clock()
            self._last_line = self._t0 - PLAIN_INTERVAL  # (the first call prints a line)
        if self.terminal:
            from tqdm import tqdm

            if self._bar is None:
                self._bar = tqdm(total=total, desc=stage, unit="kernel", file=self.stream,
                                 ncols=min(shutil.get_terminal_size((100, 24)).columns or 100,
                                           120), mininterval=0.5)
            self._bar.n = total if finished else done
            self._bar.refresh()
            if finished:
                self.close()
            return
        now = self.clock()
        if finished or now - self._last_line >= PLAIN_INTERVAL:
            self._last_line = now
            text = f"bake: {stage}: {total if finished else done}/{total} kernels"
            text += (f", done in {_duration(now - self._t0)}" if finished
                     else f", {_duration(now - self._t0)} so far")
            print(text, file=self.stream, flush=True)

    def line(self, stage: str, p: Progress, rates: tuple[float, float] | None) -> str:
        """One plain progress line."""
        pct = 100.0 * p.probes_done / p.probes_total if p.probes_total else 100.0
        text = f"bake: {stage}: {p.probes_done}/{p.probes_total} probes ({pct:.0f} %)"
        if rates is not None:
            text += f", {rates[1]:.2f} Mrays/s"
            if p.probes_done < p.probes_total and rates[0] > 0:
                text += f", about {_duration((p.probes_total - p.probes_done) / rates[0])} left"
        if p.probes_done >= p.probes_total:
            text += f", done in {_duration(self.clock() - self._t0)}"
        return text

    def _draw(self, stage: str, p: Progress, rates: tuple[float, float] | None) -> None:
        from tqdm import tqdm

        if self._bar is None:
            width = shutil.get_terminal_size(fallback=(100, 24)).columns or 100
            self._bar = tqdm(total=p.probes_total, desc=stage, unit="probe", file=self.stream,
                             ncols=min(width, 120), mininterval=0.5, initial=p.probes_done)
        self._bar.n = p.probes_done
        self._bar.set_postfix_str(f"{rates[1]:.2f} Mrays/s" if rates else "", refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def size_note(settings: BakeSettings, n_probes: int) -> str:
    """What the store will take on disk, and what the other ``--dtype`` would (the cost of each
    choice; :mod:`probegrid.bake.precision`)."""
    from probegrid.bake.settings import store_bytes

    mib = {d: store_bytes(settings, n_probes, d) / 2**20 for d in ("float", "half")}
    other = "half" if settings.dtype == "float" else "float"
    return (f"store: {mib[settings.dtype]:,.1f} MiB with {settings.dtype} maps "
            f"(--dtype {other}: {mib[other]:,.1f} MiB)")


def resume_note(out: str | os.PathLike[str]) -> str | None:
    """A line saying that a bake into ``out`` resumes an interrupted one, and from where; None
    for a fresh bake."""
    from probegrid.store import partial_path, partial_progress
    from probegrid.store.manifest import work_path

    final = Path(os.path.abspath(out))
    partial, work = partial_path(final), work_path(final)
    if partial.exists():
        try:
            done = partial_progress(final)
        except ValueError:  # a damaged partial: the bake itself will say what is wrong
            done = None
        if done is not None:
            return (f"resuming the interrupted bake of {out}: final pass, {done[0]} of "
                    f"{done[1]} probes already done")
        return f"resuming the interrupted bake of {out} (final pass)"
    kept = ([p for p in work.iterdir() if p.name != "bake.json"]  # (the key of its settings)
            if work.is_dir() and not work.is_symlink() else [])
    if kept:
        stages = sorted(p.name.removesuffix(".probes").removesuffix(".partial")
                        for p in kept if ".probes" in p.name)
        where = f" (earlier passes kept: {', '.join(stages)})" if stages else ""
        return f"resuming the interrupted bake of {out}{where}"
    return None
