"""The calibrator's threads: frames under a mutex, the solves in a worker thread outside it.

online/session.CalibratorSession is pure and single-threaded. This runner owns the two threads that
use it and the one lock between them: the frame thread (the rclpy executor) calls `process` and
`add_keyframe_matches`; the worker takes the collected work under the lock, solves WITHOUT it
(`calibration.apply` touches only the solving half), and hands the result back under the lock. So a
frame waits at most for another frame or a hand-over, never for a solve, and a result of a reference
that changed meanwhile is dropped by the session (its epoch is old). Requests that change the solving
half (set_camera_info's zoom model sample, a reset's forgetting) are queued for the worker, which runs
them before its next solve; a reset's new epoch and its deleted files are immediate. No rclpy here:
tests drive it with plain threads.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.nodes.solve_slots import SolveSlots
from ptz_selfcal.online.frames import FrameInput, FrameOutput
from ptz_selfcal.online.incremental import IncrementalCalibrator
from ptz_selfcal.online.keyframe_solver import KeyframeBundleSolver
from ptz_selfcal.online.session import CalibratorSession
from ptz_selfcal.online.work import WorkBatch, WorkResult
from ptz_selfcal.status import CALIBRATED

Array = NDArray[np.float64]


class LensWorker(Protocol):
    """A lens correction that works beside the solves (lens/): True when its estimate changed."""

    def work(self, session: SessionView) -> bool: ...


@dataclass(frozen=True)
class RunnerConfig:
    budget_s: float  # one solve step's time budget
    period_s: float  # how long the worker sleeps when nothing wakes it
    save_period_s: float  # seconds between state saves (when changed)
    slots: SolveSlots | None = None  # the machine's shared solve slots (None: no machine-wide limit)


class SessionView:
    """What the worker thread may do with the session: the solving half directly (it owns it), the
    frame path's methods through the lock."""

    def __init__(self, session: CalibratorSession, lock: threading.Lock) -> None:
        self._session, self._lock = session, lock

    @property
    def calibrator(self) -> IncrementalCalibrator | None:
        return self._session.calibration.calibrator

    @property
    def solver(self) -> KeyframeBundleSolver:
        return self._session.calibration.solver

    def add_keyframe_matches(
        self, keyframe_id: int, other_keyframe_id: int, points: Array, other: Array, H: Array | None = None
    ) -> bool:
        with self._lock:
            return self._session.add_keyframe_matches(keyframe_id, other_keyframe_id, points, other, H)

    def replace_keyframe_homographies(self, homographies: Mapping[int, Array]) -> None:
        result = self._session.calibration.replace_keyframe_homographies(homographies)
        with self._lock:
            self._session.accept(result)

    @property
    def calibrated(self) -> bool:
        with self._lock:
            return self._session.state in CALIBRATED


class SessionRunner:
    """Runs one CalibratorSession's frame path and solving half on their threads (module docstring)."""

    def __init__(
        self,
        session: CalibratorSession,
        config: RunnerConfig,
        lens: LensWorker | None = None,
        log: Callable[[str, str], None] = lambda level, text: None,
        solve: Callable[[WorkBatch, float], WorkResult] | None = None,
    ) -> None:
        self.session = session
        self.config = config
        self.lens = lens
        self.log = log  # (level, text): "info", "warning", "debug"
        self.lock = threading.Lock()
        self.view = SessionView(session, self.lock)
        self._solve = solve or session.calibration.apply  # a test may wrap it
        self.errors = 0
        self.distortion_updates = 0
        self.deferred_steps = 0  # worker steps deferred: every machine-wide solve slot was held
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._busy = False
        self._inline = False
        self._last_save = time.monotonic()
        self._thread = threading.Thread(target=self._loop, name="calibrator_solve", daemon=True)
        self._commands: list[Callable[[], None]] = []  # for the solving half, under the lock
        self._files_lock = threading.Lock()  # the state files: a save's write against a reset's delete
        self._generation = 0  # resets so far: a save taken before one is not written

    # ---- requests (the frame thread, services) --------------------------------------------------
    def set_camera_info(self, K: Array, D: Array, size: tuple[int, int]) -> tuple[bool, str]:
        """A measured K (set_camera_info) at the current zoom, the latest frame's: the prior, and a zoom
        model sample there; (False, why) when K cannot be a calibration of these images."""
        K = np.asarray(K, dtype=float).reshape(3, 3)
        D = np.resize(np.nan_to_num(np.asarray(D, dtype=float).ravel()), 5) if np.size(D) else np.zeros(5)
        with self.lock:
            problem = self.session.camera_info_problem(K, size)
            if problem:
                return False, problem
            K = K / K[2, 2]
            zoom = self.session.last_zoom
            self.session.set_prior(K, size)
            self._commands.append(lambda: self.session.calibration.anchor(zoom, K, D, size))
        self.wake()
        f = f"f = {K[1, 1]:.1f} px, pp = ({K[0, 2]:.1f}, {K[1, 2]:.1f})"
        if np.isfinite(zoom):
            return True, f"K ({f}) anchors the zoom model at zoom {zoom:g} and is the prior"
        return (
            True,
            f"K ({f}) is the prior; no zoom reading (no frame yet, or no zoom encoder): no zoom model sample",
        )

    def reset(self, why: str) -> list[Path]:
        """Start fresh: a new epoch without calibration or zoom model, and the saved state deleted;
        returns the files removed."""
        with self.lock:
            self.session.reset(why)
            self._forget()
        removed = self._remove_files()
        self.wake()
        return removed

    def _forget(self) -> None:
        """A reset's solving half's part, queued (under the lock); saves taken before it are void."""
        if self.session.take_forget():
            self._generation += 1
            self._commands.append(self.session.reset_solving_half)

    def _remove_files(self) -> list[Path]:
        with self._files_lock:
            return self.session.remove_state_files()

    def _take_commands(self) -> list[Callable[[], None]]:
        """The queued requests (under the lock), for the solving half's owner thread to run."""
        commands, self._commands = self._commands, []
        return commands

    # ---- the frame thread ------------------------------------------------------------------------
    def process(self, frame: FrameInput) -> tuple[FrameOutput, bool]:
        """The frame's calibration, and whether its homography was refused as invalid."""
        with self.lock:
            before = self.session.invalid_homographies
            out = self.session.process(frame)
            invalid = self.session.invalid_homographies > before
            stale = self.session.take_stale_state()
            if stale:
                self._forget()
        if stale:  # a swapped camera or lens: its state is not this camera's (the session warns why)
            removed = self._remove_files()
            if removed:
                self.log(
                    "warning", f"removed the saved state that does not fit: {', '.join(map(str, removed))}"
                )
            self.wake()
        return out, invalid

    def nominal_output(self, frame: FrameInput, status: str) -> FrameOutput:
        with self.lock:
            return self.session.nominal_output(frame, status)

    def add_keyframe_matches(
        self, keyframe_id: int, other_keyframe_id: int, points: Array, other: Array, H: Array | None
    ) -> bool:
        with self.lock:
            return self.session.add_keyframe_matches(keyframe_id, other_keyframe_id, points, other, H)

    def wake(self) -> None:
        self._wake.set()

    @property
    def pending(self) -> int:
        """Work not done yet, the step in progress included (0: the worker is idle)."""
        with self.lock:
            return self.session.pending_work + len(self._commands) + int(self._busy)

    def read(self, fn: Callable[[CalibratorSession], object]) -> object:
        """fn(session) under the lock, for diagnostics."""
        with self.lock:
            return fn(self.session)

    # ---- the worker ------------------------------------------------------------------------------
    def start(self, inline: bool = False) -> None:
        """The worker thread; `inline`: none, the frame thread calls `solve_inline` instead."""
        self._inline = inline
        if not inline:
            self._thread.start()

    def solve_inline(self) -> None:
        """Inline solves: finish the collected work now, on the calling (frame) thread, unpaced (the
        result must not depend on the wall clock). A first solve asks for a refinement: two steps."""
        for _ in range(3):
            if not (self._inline and self.pending):
                return
            self._guarded(lambda: self.step(paced=False))

    def step(self, paced: bool = True) -> None:
        """One worker step, with one of the machine's solve slots when paced (unpaced replays are
        deterministic and never wait for other processes); deferred, its work kept, when none is free."""
        slots = self.config.slots
        if not paced or slots is None:
            self._step(paced)
            return
        with slots.hold() as held:
            if held:
                self._step(paced)
            else:
                self.deferred_steps += 1

    def _step(self, paced: bool) -> None:
        """Take the work, solve outside the lock, hand the result back."""
        self._busy = True
        try:
            with self.lock:  # work and requests together: a reset's forgetting precedes its epoch's work
                work = self.session.take_work(paced)
                commands = self._take_commands()
                before = self.session.state
            for command in commands:
                command()
            result = self._solve(work, self.config.budget_s)
            with self.lock:
                self.session.accept(result)
            if self.lens is not None and self.lens.work(self.view):
                self.distortion_updates += 1
            with self.lock:
                after = self.session.state
                warnings = self.session.take_warnings()
                due = self.session.state_dir is not None and self.session.dirty
            if after != before:
                self.log("info", f"calibration state {before} -> {after}")
            for text in warnings:
                self.log("warning", text)
            if due and time.monotonic() - self._last_save > self.config.save_period_s:
                self.save()
        finally:
            self._busy = False

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self.config.period_s)
            self._wake.clear()
            if self._stop.is_set():
                break
            if not self._guarded(self.step):
                time.sleep(0.1)

    def _guarded(self, step: Callable[[], None]) -> bool:
        """A step that must not take its thread down: an error is counted and logged."""
        try:
            step()
        except Exception as exc:
            self.errors += 1
            self.log("warning", f"worker_error: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            return False
        return True

    def save(self) -> list[str]:
        """Save the state: taken under the lock, written outside it (a disk never stalls a frame)."""
        if self.session.state_dir is None:
            return []
        with self.lock:
            commands = self._take_commands()
        for command in commands:
            command()
        with self.lock:
            if self._commands:  # a reset came meanwhile: the solving half still holds what it drops
                return []
            if self.session.fresh:
                return []  # reset, nothing learned since: its deleted files are the state
            data, generation = self.session.to_dict(), self._generation
        with self._files_lock:
            if generation != self._generation:
                return []  # taken before a reset: not written over its deleted files
            files = self.session.write_state(data)
        with self.lock:
            self.session.mark_saved()
        self._last_save = time.monotonic()
        return files

    def stop(self, timeout: float = 30.0) -> None:
        """Stop the worker; with a state_dir, apply what was collected (no solve) and save."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout)
        if self.session.state_dir is not None:
            with self.lock:
                work = self.session.take_work()
            result = self.session.calibration.apply(work, 0.0)
            with self.lock:
                self.session.accept(result)
            self.save()
