"""Unit tests of fileio.atomic_write_text: whole-or-nothing replacement with a .bak of the previous file."""
from __future__ import annotations

import os

import pytest

from aruco_ring_localization import fileio
from aruco_ring_localization.errors import ConfigError


def _leftovers(directory):
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


def test_first_write_creates_directories_and_no_backup(tmp_path):
    path = tmp_path / "a" / "b" / "file.txt"
    fileio.atomic_write_text(str(path), "hello\n")
    assert path.read_text() == "hello\n"
    assert not (path.parent / "file.txt.bak").exists()
    assert _leftovers(path.parent) == []


def test_backup_holds_the_previous_content(tmp_path):
    path = tmp_path / "file.txt"
    for i in range(4):
        fileio.atomic_write_text(str(path), f"version {i}")
        assert path.read_text() == f"version {i}"
        if i:
            assert (tmp_path / "file.txt.bak").read_text() == f"version {i - 1}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt", "file.txt.bak"]


def test_backup_is_independent_of_the_new_file(tmp_path):
    # The .bak is a hard link to the old inode; the rename must leave it with the old bytes.
    path = tmp_path / "file.txt"
    fileio.atomic_write_text(str(path), "old")
    fileio.atomic_write_text(str(path), "new")
    assert os.stat(path).st_ino != os.stat(tmp_path / "file.txt.bak").st_ino
    assert (tmp_path / "file.txt.bak").read_text() == "old"


def test_unicode_and_pathlike(tmp_path):
    path = tmp_path / "ü.txt"
    fileio.atomic_write_text(path, "Grüße °\n")
    assert path.read_text(encoding="utf-8") == "Grüße °\n"


def test_backup_falls_back_to_copy_when_hard_links_fail(tmp_path, monkeypatch):
    path = tmp_path / "file.txt"
    fileio.atomic_write_text(str(path), "old")

    def no_link(src, dst):
        raise OSError(1, "Operation not permitted")

    monkeypatch.setattr(fileio.os, "link", no_link)
    fileio.atomic_write_text(str(path), "new")
    assert path.read_text() == "new" and (tmp_path / "file.txt.bak").read_text() == "old"


@pytest.mark.parametrize("failing", ["replace", "fsync"])
def test_failure_keeps_the_old_file_and_names_the_path(tmp_path, monkeypatch, failing):
    path = tmp_path / "file.txt"
    fileio.atomic_write_text(str(path), "old")

    def fail(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fileio.os, failing, fail)
    with pytest.raises(ConfigError) as info:
        fileio.atomic_write_text(str(path), "new")
    assert str(path) in str(info.value) and "No space left" in str(info.value), str(info.value)
    assert path.read_text() == "old"
    assert _leftovers(tmp_path) == []


def test_directory_that_cannot_be_created(tmp_path):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    path = blocker / "sub" / "file.txt"
    with pytest.raises(ConfigError) as info:
        fileio.atomic_write_text(str(path), "data")
    assert str(path) in str(info.value) and "cannot create" in str(info.value), str(info.value)


def test_temporaries_of_an_interrupted_save_are_removed_by_the_next_save(tmp_path):
    import time

    from aruco_ring_localization.fileio import atomic_write_text

    target = tmp_path / "map.yaml"
    old = tmp_path / ".map.yaml.abc123.tmp"      # what a SIGKILLed save leaves behind
    fresh = tmp_path / ".map.yaml.def456.tmp"    # a save in progress right now elsewhere
    other = tmp_path / ".other.yaml.abc123.tmp"  # another file's temporary
    for f in (old, fresh, other):
        f.write_text("partial")
    past = time.time() - 3600
    os.utime(old, (past, past))
    os.utime(other, (past, past))
    atomic_write_text(str(target), "new\n")
    assert target.read_text() == "new\n"
    assert not old.exists(), "stale temporary of map.yaml left behind"
    assert fresh.exists(), "a recent temporary (a save in progress) was removed"
    assert other.exists(), "another file's temporary was removed"


def test_new_files_get_the_umask_mode_and_replaced_files_keep_theirs(tmp_path):
    # tempfile.mkstemp would leave every map and result 0600; open() semantics are 0666 - umask.
    path = tmp_path / "result.json"
    old_umask = os.umask(0o022)
    try:
        fileio.atomic_write_text(str(path), "{}\n")
        assert oct(os.stat(path).st_mode & 0o777) == oct(0o644)
        os.umask(0o077)
        fileio.atomic_write_text(str(tmp_path / "private.json"), "{}\n")
        assert oct(os.stat(tmp_path / "private.json").st_mode & 0o777) == oct(0o600)
        os.chmod(path, 0o640)
        fileio.atomic_write_text(str(path), "{\"a\": 1}\n")  # umask 077 now: the file keeps its 0640
        assert oct(os.stat(path).st_mode & 0o777) == oct(0o640)
        assert oct(os.stat(str(path) + ".bak").st_mode & 0o777) == oct(0o640)
    finally:
        os.umask(old_umask)
    assert _leftovers(tmp_path) == []
