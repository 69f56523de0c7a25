"""Deleting and publishing directories without following links and without an instant where
the published path is missing (probegrid._fs)."""

from __future__ import annotations

import sys
import threading

import pytest

from probegrid import _fs


def _dir(path, text):
    path.mkdir()
    (path / "f").write_text(text)
    return path


def test_remove_path_unlinks_a_link_and_keeps_its_target(tmp_path):
    target = _dir(tmp_path / "precious", "keep")
    link = tmp_path / "link"
    link.symlink_to(target)
    _fs.remove_path(link)
    assert not link.is_symlink() and not link.exists()
    assert (target / "f").read_text() == "keep"
    inner = _dir(tmp_path / "d", "x")
    (inner / "to-precious").symlink_to(target)
    _fs.remove_path(inner)
    assert not inner.exists()
    assert (target / "f").read_text() == "keep"
    _fs.remove_path(tmp_path / "missing")  # no error


@pytest.mark.parametrize("exchange", [True, False])
def test_publish_replaces_and_deletes_the_old_directory(tmp_path, exchange):
    final = _dir(tmp_path / "s.probes", "old")
    staged = _dir(tmp_path / "s.probes.partial", "new")
    _fs.publish_directory(staged, final, exchange=exchange)
    assert (final / "f").read_text() == "new"
    assert not staged.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.probes"]


def test_publish_over_a_link_replaces_the_link_not_its_target(tmp_path):
    target = _dir(tmp_path / "elsewhere", "theirs")
    final = tmp_path / "s.probes"
    final.symlink_to(target)
    _fs.publish_directory(_dir(tmp_path / "s.probes.partial", "new"), final)
    assert not final.is_symlink() and (final / "f").read_text() == "new"
    assert (target / "f").read_text() == "theirs"


@pytest.mark.slow
def test_the_published_path_always_holds_a_store(tmp_path):
    """A reader polling the path while it is replaced 200 times never finds it missing
    (renameat2 RENAME_EXCHANGE on Linux)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("RENAME_EXCHANGE is Linux's")
    final = _dir(tmp_path / "s.probes", "0")
    stop = threading.Event()
    missing = []

    def poll():
        while not stop.is_set():
            if not (final / "f").exists():
                missing.append(1)

    t = threading.Thread(target=poll)
    t.start()
    try:
        for k in range(1, 201):
            _fs.publish_directory(_dir(tmp_path / "s.probes.partial", str(k)), final)
    finally:
        stop.set()
        t.join()
    assert (final / "f").read_text() == "200"
    assert missing == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.probes"]


def test_recover_publish_puts_the_old_store_back_after_a_crash_between_two_renames(tmp_path):
    final = tmp_path / "s.probes"
    _dir(tmp_path / "s.probes.replaced-4242", "old")  # the old store, renamed aside
    _fs.recover_publish(final)
    assert (final / "f").read_text() == "old"
    # with a store at the path, a leftover aside copy is deleted
    _dir(tmp_path / "s.probes.replaced-77", "older")
    _fs.recover_publish(final)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.probes"]
    assert (final / "f").read_text() == "old"
