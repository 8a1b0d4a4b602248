"""Atomic output writes: whole or not there, and only regular files are replaced."""

import os
import re
import socket

import pytest

from labcal import atomicio


def test_replaces_a_regular_file_and_keeps_its_mode(tmp_path):
    p = tmp_path / "a.script"
    p.write_text("old")
    os.chmod(p, 0o600)
    atomicio.write_text(p, "new")
    assert p.read_text() == "new"
    assert (os.stat(p).st_mode & 0o777) == 0o600
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.script"]


@pytest.mark.parametrize("kind", ["symlink", "folder", "fifo", "socket"])
def test_refuses_what_is_not_a_regular_file(tmp_path, kind):
    p = tmp_path / "out"
    target = tmp_path / "victim"
    target.write_text("keep")
    if kind == "symlink":
        p.symlink_to(target)
    elif kind == "folder":
        p.mkdir()
    elif kind == "fifo":
        os.mkfifo(p)
    else:
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(p))
    with pytest.raises(atomicio.UnsafeTargetError, match=re.escape(str(p))):
        atomicio.write_text(p, "x")
    assert target.read_text() == "keep"
    assert os.path.lexists(p)
    assert p.is_symlink() or not p.is_file()


def test_refuses_a_device():
    with pytest.raises(atomicio.UnsafeTargetError, match="device"):
        atomicio.write_text("/dev/null", "x")
    assert os.path.exists("/dev/null") and not os.path.isfile("/dev/null")


def test_missing_folder_is_named(tmp_path):
    with pytest.raises(atomicio.UnsafeTargetError, match="does not exist"):
        atomicio.write_text(tmp_path / "nope" / "x.json", "x")


def test_a_failed_write_leaves_the_old_file_and_no_temp(tmp_path, monkeypatch):
    p = tmp_path / "prog.csv"
    p.write_text("old program")
    real_write = os.write

    def full_disk(fd, data):
        real_write(fd, bytes(data[:10]))
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "write", full_disk)
    with pytest.raises(OSError, match=r"prog\.csv"):
        atomicio.write_text(p, "a new program much longer than ten bytes")
    monkeypatch.undo()
    assert p.read_text() == "old program"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["prog.csv"]
