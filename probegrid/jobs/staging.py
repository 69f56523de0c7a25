"""Outputs written in a staging folder and moved into place only when complete.

``probegrid filter`` and ``probegrid export`` write many files. :func:`staged_output` gives them
a private staging folder, ``.NAME.staging-PID`` beside the output directory ``NAME`` (same file
system, so the final moves are renames), created *before* any work starts: an output location
that cannot be written (a missing or read-only parent, ``/proc``) is a one-line error in words
at once, not after the computation. When the job's block ends normally the staged files are
moved into place:

* a new output directory: the staging folder is renamed to ``NAME`` in one step (a reader sees
  no directory, or the finished one);
* an earlier output of the same kind (the only other case
  :func:`probegrid.jobs.filter.prepare_output_dir` allows): its ``manifest.json`` is removed
  first, then the files it lists that the new output does not write (an earlier run's
  ``specular_m7`` beside a new 6-level chain: :func:`remove_stale`), each staged file is
  renamed over its old namesake, and the new ``manifest.json`` moved last, so a directory with
  a manifest always holds a finished output and nothing of an earlier one; files the earlier
  manifest does not list (the user's own) are left alone.

When the block raises (a bad option found late, a full disk, Ctrl-C, SIGTERM), the staging
folder and every directory created for it are removed and an earlier output is left exactly as
it was: no failure leaves temporary files or a half-written output.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from probegrid._fs import fsync_dir

__all__ = ["MANIFEST", "check_writable_location", "listed_files", "remove_stale",
           "staged_output", "staging_path"]

#: The file written last into an output directory: its presence marks a finished output.
MANIFEST = "manifest.json"


def listed_files(out: str | os.PathLike[str]) -> set[str]:
    """The files the ``manifest.json`` in ``out`` says its output wrote, as paths relative to
    ``out`` (``files[].path``, a name or a list of names, and ``probes[].folder`` with its
    ``files``, as every probegrid output manifest lists them); empty when there is no readable
    manifest. Names that would leave ``out`` (absolute, ``..``) are not returned."""
    try:
        doc = json.loads((Path(out) / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return set()
    found: set[str] = set()

    def add(entries: object, folder: str = "") -> None:
        for entry in entries if isinstance(entries, list) else ():
            path = entry.get("path") if isinstance(entry, dict) else None
            for name in path if isinstance(path, list) else [path]:
                if isinstance(name, str) and name:
                    found.add(os.path.join(folder, name) if folder else name)

    if isinstance(doc, dict):
        add(doc.get("files"))
        probes = doc.get("probes")
        for probe in probes if isinstance(probes, list) else ():
            folder = probe.get("folder") if isinstance(probe, dict) else None
            if isinstance(folder, str) and folder:
                add(probe.get("files"), folder)
    return {n for n in found if not os.path.isabs(n)
            and ".." not in Path(n).parts and Path(n).parts}


def remove_stale(out: str | os.PathLike[str], previous: set[str], kept: set[str]) -> list[str]:
    """Remove from ``out`` the files of ``previous`` (an earlier output's :func:`listed_files`)
    that the new output does not write (not in ``kept``, paths relative to ``out``), and the
    folders that leaves empty; only regular files and links are removed, never a directory's
    content the manifest did not list. Returns the removed paths."""
    base = Path(out)
    removed: list[str] = []
    for name in sorted(previous - kept):
        path = base / name
        if path.is_symlink() or path.is_file():
            path.unlink()
            removed.append(name)
            parent = path.parent
            while parent != base and parent.is_dir() and not any(parent.iterdir()):
                parent.rmdir()
                parent = parent.parent
    return removed


def staging_path(out: str | os.PathLike[str]) -> Path:
    """The staging folder of output directory ``out``: ``.NAME.staging-PID`` beside it."""
    full = Path(os.path.abspath(out))
    return full.with_name(f".{full.name}.staging-{os.getpid()}")


def _words(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def check_writable_location(out: str | os.PathLike[str], what: str = "output") -> None:
    """Refuse (one-line ``ValueError`` in words) an output path whose directory cannot be made:
    its nearest existing ancestor must be a directory in which a new directory can be created
    (tried for real, then removed; ``/proc``, read-only mounts and files fail here)."""
    final = Path(os.path.abspath(out))
    parent = final.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"cannot create the {what} {out}: {parent} is not a directory")
    try:
        probe = Path(tempfile.mkdtemp(prefix=f".{final.name}.check-", dir=parent))
    except OSError as exc:
        raise ValueError(f"cannot create the {what} {out}: {_words(exc)} (in {parent})") from None
    probe.rmdir()


def _make_dirs(directory: Path) -> list[Path]:
    """Create ``directory`` and its missing parents; returns the created ones, deepest last."""
    missing: list[Path] = []
    d = directory
    while not d.exists() and d != d.parent:
        missing.append(d)
        d = d.parent
    created: list[Path] = []
    try:
        for d in reversed(missing):
            d.mkdir()
            created.append(d)
    except OSError:
        for d in reversed(created):
            d.rmdir()
        raise
    return created


@contextmanager
def staged_output(out: str | os.PathLike[str],
                  prepare: Callable[[Path], object] | None = None) -> Iterator[Path]:
    """Yield a new, empty staging folder for output directory ``out``; move its files into
    place when the block ends normally, remove it when the block raises (module docstring).

    ``prepare(out)``, if given, is called just before the files move (e.g. to check ``out``
    again and remove an earlier output's manifest). Raises ``ValueError`` (one line, in words)
    when the staging folder cannot be created.
    """
    final = Path(os.path.abspath(out))
    staging = staging_path(final)
    try:
        created = _make_dirs(final.parent)
    except OSError as exc:
        raise ValueError(f"cannot create the output directory {out}: {_words(exc)}") from None
    try:
        staging.mkdir()
    except OSError as exc:
        for d in reversed(created):
            d.rmdir()
        raise ValueError(f"cannot create the output directory {out}: {_words(exc)} (in "
                         f"{final.parent})") from None
    try:
        yield staging
        if prepare is not None:
            prepare(final)
        _commit(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if not final.exists():
            for d in reversed(created):
                try:
                    d.rmdir()
                except OSError:
                    break
        raise


def _commit(staging: Path, final: Path) -> None:
    """Move the staged files into ``final`` (see the module docstring)."""
    for entry in staging.iterdir():  # every staged file is on disk before it is published
        if entry.is_file():
            fd = os.open(entry, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
    fsync_dir(staging)
    if not final.exists():
        try:
            staging.rename(final)
        except OSError:  # created meanwhile (a concurrent run): fall through to the merge
            if not final.is_dir():
                raise
        else:
            fsync_dir(final.parent)
            return
    previous = listed_files(final)
    (final / MANIFEST).unlink(missing_ok=True)
    fsync_dir(final)
    kept = {str(p.relative_to(staging)) for p in staging.rglob("*") if not p.is_dir()}
    remove_stale(final, previous, kept)
    names = sorted(p.name for p in staging.iterdir())
    for name in [n for n in names if n != MANIFEST] + [n for n in names if n == MANIFEST]:
        _move(staging / name, final / name)
    fsync_dir(final)
    staging.rmdir()


def _move(source: Path, target: Path) -> None:
    """Rename ``source`` over ``target``; a folder onto an existing folder is merged (its files
    renamed one by one, the target's other files left alone)."""
    if source.is_dir() and not source.is_symlink() and target.is_dir() \
            and not target.is_symlink():
        for child in sorted(source.iterdir()):
            _move(child, target / child.name)
        fsync_dir(target)
        source.rmdir()
        return
    os.replace(source, target)
