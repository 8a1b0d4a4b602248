"""The README's scripting snippet, run as written: it must pick the newest session of the user's store, never the
shipped example (whose id sorted after every dated one), and write its fit there."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from cli_testutil import TARGETS, invoke, last_line

from labcal.datasets import SessionStore

ROOT = Path(__file__).resolve().parents[2]


def scripting_snippet() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("**Scripting labcal.**") :]
    match = re.search(r"```sh\n(.*?)```", section, re.S)
    assert match, "the README's scripting section has no sh block"
    return match.group(1)


def test_session_list_is_oldest_first_with_the_example_first(tmp_path):
    store = tmp_path / "store"
    shutil.copytree(ROOT / "sessions" / "example", store / "example")
    (tmp_path / "targets.toml").write_text(TARGETS)
    r = invoke("session", "new", "--robot", "ur10", "--targets", tmp_path / "targets.toml", "--poses", 12, store=store)
    assert r.exit_code == 0, r.stderr
    ids = [info.session_id for info in SessionStore(store).list_sessions()]
    assert ids == ["example", last_line(r).split("@")[0]]


@pytest.mark.slow  # a real `fit --method auto` in a subprocess, as the README runs it
@pytest.mark.skipif(shutil.which("jq") is None or shutil.which("bash") is None, reason="the snippet needs bash and jq")
def test_readme_scripting_snippet_fits_the_newest_session_of_the_users_store(tmp_path):
    bin_dir = Path(sys.executable).parent
    if not (bin_dir / "labcal").exists():
        pytest.skip("the labcal console script is not installed beside this interpreter")
    store = tmp_path / "labcal-sessions"  # where the snippet's LABCAL_STORE points with HOME=tmp_path
    shutil.copytree(ROOT / "sessions" / "example", store / "example")
    (tmp_path / "targets.toml").write_text(TARGETS)
    r = invoke("session", "new", "--robot", "ur10", "--targets", tmp_path / "targets.toml", "--poses", 14, store=store)
    assert r.exit_code == 0, r.stderr
    newest = last_line(r)
    env = {**os.environ, "HOME": str(tmp_path), "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}
    env.pop("LABCAL_STORE", None)
    run = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", scripting_snippet()],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    assert "damaged" not in run.stdout
    fit = json.loads((tmp_path / "fit.json").read_text())
    assert fit["schema"] == "labcal.fit/1"
    stored = SessionStore(store)
    assert [f.fit_id for f in stored.list_fits(newest)] == [fit["fit_id"]]
    assert not (store / "example" / "v001" / "fits").exists(), "the snippet wrote into the shipped example"
