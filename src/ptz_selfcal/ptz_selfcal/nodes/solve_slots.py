"""A machine's solve slots: at most `count` calibrators re-optimise at once, however many cameras (suites)
the machine runs, so that N cameras cannot claim more cores for their solves than the machine has.

One lock file per slot in a directory every suite on the machine shares, held with flock(2) for one
worker step: the kernel releases it when the holder's process dies, so a killed calibrator never keeps
a slot. A worker that finds every slot held defers its step (its work stays queued) and tries again at
its next wake-up; frames never wait for a slot, they are served from the latest calibration.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


def default_slot_count() -> int:
    """Half the machine's cores, at least one: the other half stays for the frames."""
    return max(1, (os.cpu_count() or 2) // 2)


def default_slot_dir() -> Path:
    """Shared by every user's suites on the machine: /dev/shm where it exists (memory, no disk)."""
    shm = Path("/dev/shm")
    return (shm if shm.is_dir() else Path(tempfile.gettempdir())) / "ptz_selfcal_solve_slots"


class SolveSlots:
    def __init__(self, directory: str | os.PathLike[str], count: int) -> None:
        if count < 1:
            raise ValueError(f"solve slots: {count} (at least 1)")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.paths = [self.directory / f"slot{i}.lock" for i in range(count)]
        self._start = os.getpid() % count  # suites start their search at different slots

    @contextlib.contextmanager
    def hold(self) -> Iterator[bool]:
        """A free slot for the duration of the block (True), or none free now (False)."""
        fd = self._take()
        try:
            yield fd is not None
        finally:
            if fd is not None:
                os.close(fd)  # closing the descriptor releases its flock

    def _take(self) -> int | None:
        n = len(self.paths)
        for i in range(n):
            fd = os.open(self.paths[(self._start + i) % n], os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return fd
            except BlockingIOError:
                os.close(fd)
        return None
