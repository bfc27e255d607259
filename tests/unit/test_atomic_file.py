"""persist/atomic_file.py: temporary files of a write interrupted by a kill are recognisable and removed at
the next start (the calibrator's state load), those of a live writer and unrelated files are kept."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

from ptz_selfcal.online import session as cs
from ptz_selfcal.persist.atomic_file import TEMP_SUFFIX, atomic_write_text, remove_stale_temporaries
from ptz_selfcal.persist.state_files import STATE_FILE

SRC = str(Path(cs.__file__).resolve().parents[2])


def dead_pid() -> int:
    """The pid of a process that has exited (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def kill_during_save(state_dir: Path) -> Path:
    """A real process SIGKILLed between writing a state file's temporary and renaming it."""
    child = textwrap.dedent(
        f"""
        import os, sys, time
        sys.path.insert(0, {SRC!r})
        from ptz_selfcal.persist import atomic_file
        def hang(src, dst):
            print("written", flush=True)
            time.sleep(60)
        atomic_file.os.replace = hang
        atomic_file.atomic_write_text({str(state_dir / STATE_FILE)!r}, "calibrator: new\\n")
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "written"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(10)
    (tmp,) = [p for p in state_dir.iterdir() if p.name.endswith(TEMP_SUFFIX)]
    assert tmp.name.startswith(f".{STATE_FILE}.{proc.pid}."), tmp.name
    return tmp


def test_temporary_of_a_killed_save_is_removed_at_the_next_state_load(tmp_path: Path) -> None:
    session = cs.CalibratorSession(cs.SessionConfig(), state_dir=tmp_path)
    session.save()
    saved = (tmp_path / STATE_FILE).read_bytes()
    tmp = kill_during_save(tmp_path)
    assert (tmp_path / STATE_FILE).read_bytes() == saved  # the kill left the old state in place
    restarted = cs.CalibratorSession(cs.SessionConfig(), state_dir=tmp_path)
    messages = restarted.restore()
    assert not tmp.exists()
    assert any(str(tmp) in m and "interrupted by a kill" in m for m in messages), messages
    assert sorted(p.name for p in tmp_path.iterdir()) == [STATE_FILE]


def test_only_temporaries_of_writers_that_are_gone_are_removed(tmp_path: Path) -> None:
    gone = tmp_path / f".state.yaml.{dead_pid()}.abc123{TEMP_SUFFIX}"
    mine = tmp_path / f".state.yaml.{os.getpid()}.def456{TEMP_SUFFIX}"  # a write in progress
    parent = tmp_path / f".zoom_model.yaml.{os.getppid()}.x_9{TEMP_SUFFIX}"  # a live process's
    old = tmp_path / f".zoom_model.yaml.{os.getppid()}.old{TEMP_SUFFIX}"  # live pid, but two hours old
    unrelated = [tmp_path / name for name in ("state.yaml", ".notes.tmp", f".x.y{TEMP_SUFFIX}", "a.tmp")]
    for path in (gone, mine, parent, old, *unrelated):
        path.write_text("x")
    two_hours_ago = time.time() - 7200
    os.utime(old, (two_hours_ago, two_hours_ago))
    assert sorted(remove_stale_temporaries(tmp_path)) == sorted([gone, old])
    assert not gone.exists() and not old.exists()
    assert mine.exists() and parent.exists() and all(p.exists() for p in unrelated)
    assert remove_stale_temporaries(tmp_path / "missing") == []


def test_write_leaves_no_temporary_and_names_them_recognisably(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "state.yaml"
    atomic_write_text(path, "a: 1\n")
    assert path.read_text() == "a: 1\n" and os.listdir(tmp_path) == ["state.yaml"]
    seen: list[str] = []
    real_replace = os.replace

    def spy(src, dst):
        seen.append(Path(src).name)
        real_replace(src, dst)

    monkeypatch.setattr("ptz_selfcal.persist.atomic_file.os.replace", spy)
    atomic_write_text(path, "a: 2\n")
    assert seen[0].startswith(f".state.yaml.{os.getpid()}.") and seen[0].endswith(TEMP_SUFFIX)
    assert path.read_text() == "a: 2\n" and os.listdir(tmp_path) == ["state.yaml"]
