"""Disk faults: a full or unwritable output folder fails in one line, at the start or at a
checkpoint write, and the last good checkpoint is never replaced by a partial one.

The write errors are injected (a full disk cannot be made without privileges here): the
checkpoint's bytes are half written and then ``ENOSPC`` is raised, or ``fsync`` / the rename
fail (docs/deployment.md).
"""

from __future__ import annotations

import errno
import io
import os
import subprocess
import sys
from pathlib import Path

import pytest

from kimera_multi_py.agent import checkpoint
from kimera_multi_py.agent.checkpoint import Snapshot, load_checkpoint, save_checkpoint
from kimera_multi_py.core.errors import CheckpointError, ConfigError
from kimera_multi_py.io import outdir
from kimera_multi_py.io.outdir import ensure_writable

REPO = Path(__file__).resolve().parents[2]
OLD = REPO / "tests" / "data" / "agent_tiny_v6.kmc"


def _full(*_args: object, **_kw: object) -> None:
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _io_error(*_args: object, **_kw: object) -> None:
    raise OSError(errno.EIO, os.strerror(errno.EIO))


@pytest.fixture(scope="module")
def agent():  # type: ignore[no-untyped-def]
    return load_checkpoint(OLD)[0]


@pytest.mark.parametrize("fault", ["half-written", "fsync", "rename"])
def test_a_failed_checkpoint_write_keeps_the_last_good_one(agent, tmp_path: Path, fault: str,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "robot0" / "checkpoint.kmc"
    path.parent.mkdir()
    save_checkpoint(path, agent, {"next": 1})
    good = path.read_bytes()
    if fault == "half-written":
        real = Snapshot.write_to

        def half(self: Snapshot, fh, compress: bool = True) -> None:  # type: ignore[no-untyped-def]
            buf = io.BytesIO()
            real(self, buf, compress)
            fh.write(buf.getvalue()[: len(buf.getvalue()) // 2])
            _full()

        monkeypatch.setattr(Snapshot, "write_to", half)
    else:
        monkeypatch.setattr(checkpoint.os, "fsync" if fault == "fsync" else "replace",
                            _full if fault == "fsync" else _io_error)
    with pytest.raises(CheckpointError) as err:
        save_checkpoint(path, agent, {"next": 2})
    message = str(err.value)
    assert "\n" not in message and str(path) in message and "cannot write checkpoint" in message
    assert os.strerror(errno.EIO if fault == "rename" else errno.ENOSPC) in message
    monkeypatch.undo()
    assert path.read_bytes() == good  # the last good checkpoint, whole
    assert load_checkpoint(path)[1]["next"] == 1
    assert [p.name for p in path.parent.iterdir()] == ["checkpoint.kmc"]  # no partial file left


def test_an_unwritable_or_full_folder_is_found_at_the_start(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    ok = ensure_writable(tmp_path / "a" / "b")
    assert ok.is_dir() and list(ok.iterdir()) == []
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(ConfigError, match=r"^out: cannot create .*file/robot0: Not a directory$"):
        ensure_writable(blocker / "robot0")
    monkeypatch.setattr(outdir.os, "write", _full)
    with pytest.raises(ConfigError, match=r"^out: cannot write into .*: No space left on device$"):
        ensure_writable(ok)
    monkeypatch.undo()
    assert list(ok.iterdir()) == []  # the probe is removed


def test_the_agent_command_fails_in_one_line_on_an_unwritable_out(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    proc = subprocess.run([sys.executable, "-m", "kimera_multi_py.cli.main", "agent", "--robot", "0", "--source",
                           f"sim:{REPO / 'sims' / 'tiny.toml'}", "--out", str(blocker / "run"), "--connect",
                           "tcp/127.0.0.1:9"], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 1
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "cannot create" in lines[0] and "Not a directory" in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
