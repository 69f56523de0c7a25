"""``probegrid demo``: the main job on the bundled sample data, with nothing to set up.

1. Filters the bundled sky (``data/sample_sky.hdr``, made by :mod:`probegrid.jobs.samples`) into
   diffuse and specular maps, SH, the DFG LUT and PNG previews.
2. Bakes the bundled room (``data/sample_room.glb``: coloured walls, an emissive ceiling panel,
   a point lamp and a window onto that sky) into a probe grid store, unless it exists already.
3. Serves the store over HTTP (``--no-serve`` stops after step 2) and prints a query to try.

The repository's ``data/`` files are used as they are when present (a checkout); an installed
package without them regenerates them from code into a per-user cache once.
Before the store is served the command stops the fork server the bake's workers came from
(:func:`probegrid.bake.executors.local.stop_fork_server`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

__all__ = ["run_demo", "sample_data_dir"]

Progress = Callable[[str], None]


def sample_data_dir() -> Path:
    """The repository's ``data/`` directory, or a per-user cache when not run from a checkout."""
    repo_data = Path(__file__).resolve().parents[2] / "data"  # (probegrid/jobs/demo.py)
    if (repo_data / "sample_room.glb").is_file() and (repo_data / "sample_sky.hdr").is_file():
        return repo_data
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "probegrid" / "data"
    if not ((cache / "sample_room.glb").is_file() and (cache / "sample_sky.hdr").is_file()):
        from probegrid.jobs.samples import write_sample_data

        cache.mkdir(parents=True, exist_ok=True)
        write_sample_data(cache)
    return cache


def run_demo(out: str | os.PathLike[str], *, progress: Progress | None = None,
             workers: int | None = None, grid: str = "8x6x8", face_size: int = 16) -> str:
    """Run steps 1 and 2; returns a report of what was made and how to look at it."""
    from probegrid.bake import BakeSettings
    from probegrid.filter import FilterSettings
    from probegrid.jobs.bake import BakeJob, run_bake
    from probegrid.jobs.filter import run_filter
    from probegrid.store import open_store

    say = progress or (lambda _m: None)
    data = sample_data_dir()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lines = []

    say(f"[1/2] filtering {data / 'sample_sky.hdr'}")
    fr = run_filter(data / "sample_sky.hdr", out / "sky",
                    FilterSettings(size=64, diffuse_size=16), progress=say)
    lines += ["Filtered environment:", fr.summary(), ""]

    store = out / "sample_room.probes"
    if store.exists():
        say(f"[2/2] {store} exists; delete it to bake again")
        s = open_store(store)
        lines += [f"Probe grid store (existing): {store} ({s.grid.label} probes)"]
    else:
        say(f"[2/2] baking {data / 'sample_room.glb'} ({grid}, {face_size}^2 faces, 2 bounces)")
        report = run_bake(BakeJob(
            scene=data / "sample_room.glb", out=store, grid=grid,
            settings=BakeSettings(face_size=face_size, bounces=2),
            environment=[data / "sample_sky.hdr"], workers=workers,
        ))
        lines += ["Probe grid store:", report.summary()]
    lines += [
        "",
        "Look at it:",
        (f"  previews:       {out / 'sky' / 'preview_specular.png'}, "
        f"{out / 'sky' / 'preview_diffuse.png'}"),
        f"  store manifest: probegrid info {store}",
        f"  one probe:      probegrid export {store} --probe 4,2,4 --out {out / 'probe_4_2_4'}",
    ]
    return "\n".join(lines)
