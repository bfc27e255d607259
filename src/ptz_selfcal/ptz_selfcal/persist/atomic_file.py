"""Files replaced atomically: a reader (or a restart after a kill) sees the old or the new content.

The temporary file of a write is named `.<target name>.<writer pid>.<random>.atomic.tmp` beside the target,
so that one left by a writer killed between its creation and the rename is recognisable (and its writer
known): remove_stale_temporaries() removes those whose writer is gone, e.g. at a restart.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import time
from pathlib import Path

TEMP_SUFFIX = ".atomic.tmp"


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Replace `path` with `text`: temp file in the same directory, fsync, os.replace, fsync the directory."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Replace `path` with `data`, as atomic_write_text does."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=TEMP_SUFFIX, dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # make the rename itself durable (not possible on every platform)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def _writer_pid(name: str) -> int | None:
    """The writer's pid in a temporary file's name, None if the name is not one of ours."""
    if not (name.startswith(".") and name.endswith(TEMP_SUFFIX)):
        return None
    parts = name[: -len(TEMP_SUFFIX)].rsplit(".", 2)  # ".<target>", "<pid>", "<random>"
    if len(parts) != 3 or not parts[0] or not parts[1].isdigit():
        return None
    return int(parts[1])


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: a process of another user has that pid
        return True
    return True


def remove_stale_temporaries(directory: str | os.PathLike[str], max_age_s: float = 3600.0) -> list[Path]:
    """Remove the temporary files of atomic_write_text in `directory` whose writer is no longer running
    (or that are older than max_age_s, in case its pid was reused); returns the files removed. Other
    files, and those of a writer still running, are left alone."""
    directory = Path(directory)
    removed: list[Path] = []
    if not directory.is_dir():
        return removed
    now = time.time()
    for tmp in sorted(directory.glob(f".*{TEMP_SUFFIX}")):
        pid = _writer_pid(tmp.name)
        if pid is None:
            continue
        with contextlib.suppress(OSError):  # gone meanwhile, or not ours to remove
            if not _alive(pid) or now - tmp.stat().st_mtime > max_age_s:
                tmp.unlink()
                removed.append(tmp)
    return removed
