"""How the store makes things durable, observed from outside: which files and folders are fsynced, and in which
order with the rename that publishes a version; what a journal refuses to do after a failed write; and the canonical
JSON every hash is taken over. Found by the mutation benchmark (benchmarks/mutation.py): dropping any of these
left every other test green."""

from __future__ import annotations

import math
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from datasets_testutil import fake_measurement, new_journal

from labcal.datasets import Journal, JournalError, SessionHeader, SessionStore
from labcal.datasets._util import canonical_json, publish_dir


class FsSpy:
    """Records, in order, every fsync (inode and whether it is a folder) and every rename done through ``os``."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.events: list[tuple[str, int, bool]] = []
        real_fsync, real_rename = os.fsync, os.rename

        def fsync(fd):
            st = os.fstat(fd)
            self.events.append(("fsync", st.st_ino, stat.S_ISDIR(st.st_mode)))
            return real_fsync(fd)

        def rename(src, dst, *a, **kw):
            ino = os.stat(src).st_ino
            real_rename(src, dst, *a, **kw)
            self.events.append(("rename", ino, os.path.isdir(dst)))

        monkeypatch.setattr(os, "fsync", fsync)
        monkeypatch.setattr(os, "rename", rename)

    def index(self, kind: str, ino: int) -> int:
        hits = [i for i, (k, n, _) in enumerate(self.events) if k == kind and n == ino]
        assert hits, f"no {kind} of inode {ino} in {self.events}"
        return hits[-1]


def test_a_new_journal_and_its_folder_entry_are_fsynced(tmp_path, monkeypatch):
    spy = FsSpy(monkeypatch)
    store = SessionStore(tmp_path)
    with new_journal(store) as j:
        path = Path(j.path)
    spy.index("fsync", path.stat().st_ino)  # the start document
    spy.index("fsync", path.parent.stat().st_ino)  # the session folder holding the journal's name
    spy.index("fsync", tmp_path.stat().st_ino)  # the store folder holding the session's name


def test_sealing_fsyncs_every_file_before_the_rename_and_the_session_folder_after(tmp_path, monkeypatch):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(0)
    with new_journal(store) as j:
        for i in range(3):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
        sid = j.session_id
    spy = FsSpy(monkeypatch)
    vdir = store.version_dir(store.seal(sid).ref)
    published = spy.index("rename", vdir.stat().st_ino)
    for name in ("measurements.parquet", "manifest.json"):
        assert spy.index("fsync", (vdir / name).stat().st_ino) < published, name
    assert spy.index("fsync", vdir.stat().st_ino) < published  # the version folder's own entries
    assert spy.index("fsync", vdir.parent.stat().st_ino) > published  # the new name vNNN itself


def test_publishing_refuses_a_name_that_is_taken_even_by_an_empty_folder(tmp_path):
    tmp, final = tmp_path / ".tmp-v001-x", tmp_path / "v001"
    tmp.mkdir()
    (tmp / "data").write_bytes(b"new")
    final.mkdir()  # e.g. left by a concurrent writer: os.rename alone would silently replace it
    with pytest.raises(FileExistsError, match="v001 already exists"):
        publish_dir(tmp, final)
    assert (tmp / "data").read_bytes() == b"new" and list(final.iterdir()) == []


def test_creating_a_journal_where_one_exists_is_refused_and_changes_nothing(tmp_path):
    store = SessionStore(tmp_path)
    with new_journal(store) as j:
        path, header_line = Path(j.path), Path(j.path).read_bytes()
    header = SessionHeader.of("ur10", "5" * 64, 6, targets=[[0, 0, 0]], frame="base")
    with pytest.raises(JournalError, match="already exists"):
        Journal.create(path, header, session_id="other")
    assert path.read_bytes() == header_line


def test_after_a_failed_write_the_journal_refuses_more_appends_until_reopened(tmp_path, monkeypatch):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(1)
    j = new_journal(store)
    j.append_measurement(pose_index=0, **fake_measurement(rng))
    real_write = os.write

    def full_disk(fd, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "write", full_disk)
    with pytest.raises(JournalError, match="No space left"):
        j.append_measurement(pose_index=1, **fake_measurement(rng))
    monkeypatch.setattr(os, "write", real_write)
    # The disk has room again, but what reached it of the failed line is unknown: only a reopen (which repairs a
    # torn line) may write again.
    with pytest.raises(JournalError, match=r"previous write .* failed; reopen"):
        j.append_measurement(pose_index=1, **fake_measurement(rng))
    sid = j.session_id
    j.close()
    with store.open_journal(sid) as j2:
        assert j2.append_measurement(pose_index=1, **fake_measurement(rng)).seq == 2


def test_canonical_json_does_not_depend_on_key_order_and_refuses_nan():
    a = canonical_json({"b": 1, "a": {"y": [1.5, None], "x": "é"}})
    b = canonical_json({"a": {"x": "é", "y": [1.5, None]}, "b": 1})
    assert a == b == '{"a":{"x":"é","y":[1.5,null]},"b":1}'
    with pytest.raises(ValueError):
        canonical_json({"q": math.nan})


def test_a_nan_in_the_start_document_is_refused_and_leaves_no_session(tmp_path):
    store = SessionStore(tmp_path)
    header = SessionHeader.of("ur10", "5" * 64, 6, targets=[[0, 0, 0]], frame="base",
                              metadata={"temperature": math.nan}, session_id="nan-session")  # fmt: skip
    with pytest.raises(JournalError, match="not JSON-serialisable"):
        store.create_session(header)
    assert not (tmp_path / "nan-session").exists()


def test_a_second_start_document_is_corrupt_not_a_new_session(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(2)
    with new_journal(store) as j:
        j.append_measurement(pose_index=0, **fake_measurement(rng))
        path, sid = Path(j.path), j.session_id
    start = path.read_bytes().split(b"\n")[0].replace(sid.encode(), b"other-session")
    with open(path, "ab") as f:
        f.write(start + b"\n")
    c = store.read_journal(sid)
    assert c.corrupt_lines == [3] and c.corrupt_reasons[3] == "a second start document"
    assert [d["type"] for d in c.documents] == ["start", "measurement"] and c.start.session_id == sid
    with pytest.raises(JournalError, match=r"corrupt line\(s\) \[3\]"):
        store.seal(sid)


def test_publishing_fsyncs_the_folder_that_holds_the_new_name(tmp_path, monkeypatch):
    """The rename is durable only once the parent folder is fsynced, by publish_dir itself (not by whatever the
    caller happens to write next)."""
    tmp, final = tmp_path / ".tmp-v001-x", tmp_path / "v001"
    tmp.mkdir()
    (tmp / "data").write_bytes(b"new")
    spy = FsSpy(monkeypatch)
    publish_dir(tmp, final)
    assert spy.index("fsync", tmp_path.stat().st_ino) > spy.index("rename", final.stat().st_ino)


def test_a_new_store_folder_is_fsynced_into_the_folder_that_holds_it(tmp_path, monkeypatch):
    # `labcal session new --store NEW` creates the store: until the folder holding its name is fsynced, a power loss
    # can lose the store's own entry, and with it every measurement fsynced inside it.
    spy = FsSpy(monkeypatch)
    store = SessionStore(tmp_path / "lab" / "store")
    with new_journal(store) as j:
        path = Path(j.path)
    created = spy.index("fsync", path.stat().st_ino)  # the start document
    assert spy.index("fsync", (tmp_path / "lab").stat().st_ino) < created  # holds the name "store"
    assert spy.index("fsync", tmp_path.stat().st_ino) < created  # holds the name "lab", also created here
