"""The machine's solve slots (nodes/solve_slots.py): with one slot, two calibrators' workers never solve
at once; the second defers its step (its work kept) while the first holds the slot, and solves once it is
free; with two slots both solve together. Separate open files conflict under flock as separate processes
do, so one test process stands for two suites. The solves wait on events the test controls."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from test_calibration_state import HEIGHT, WIDTH, encoded_sweep
from test_session_runner import SAFETY_S, HeldSolve

from ptz_selfcal.nodes.session_runner import RunnerConfig, SessionRunner
from ptz_selfcal.nodes.solve_slots import SolveSlots
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameInput
from ptz_selfcal.online.session import CalibratorSession
from ptz_selfcal.status import TrackingState


def _runner(slots: SolveSlots) -> tuple[SessionRunner, HeldSolve]:
    session = CalibratorSession(SessionConfig(nominal_hfov_deg=50.0))
    held = HeldSolve(session)
    runner = SessionRunner(session, RunnerConfig(5.0, 0.01, 1e9, slots), solve=held)
    _, H, zoom = encoded_sweep(20)
    for j in (0, 8):  # two keyframes: work for the worker
        frame = FrameInput(
            j / 30.0, H[j], TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, j, "ref", float(zoom[j])
        )
        runner.process(frame)
    return runner, held


def _wait(condition, seconds: float = SAFETY_S) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.005)
    return False


def test_one_slot_serialises_two_calibrators_solves(tmp_path: Path) -> None:
    a, held_a = _runner(SolveSlots(tmp_path, 1))
    b, held_b = _runner(SolveSlots(tmp_path, 1))
    a.start()
    try:
        assert held_a.started.wait(SAFETY_S)  # a holds the only slot, in its solve
        b.start()
        assert _wait(lambda: b.deferred_steps >= 3)  # b's worker woke and found no slot, thrice
        assert not held_b.started.is_set() and b.pending > 0  # its work is kept, not solved
        held_a.release.set()
        assert held_b.started.wait(SAFETY_S)  # the slot came free: b solves
        held_b.release.set()
        assert _wait(lambda: a.pending == 0 and b.pending == 0)
        assert held_a.events == ["solve ended"] and held_b.events == ["solve ended"]
    finally:
        held_a.release.set()
        held_b.release.set()
        a.stop()
        b.stop()


def test_two_slots_let_two_calibrators_solve_together(tmp_path: Path) -> None:
    a, held_a = _runner(SolveSlots(tmp_path, 2))
    b, held_b = _runner(SolveSlots(tmp_path, 2))
    a.start()
    b.start()
    try:
        assert held_a.started.wait(SAFETY_S) and held_b.started.wait(SAFETY_S)  # both in a solve at once
    finally:
        held_a.release.set()
        held_b.release.set()
        a.stop()
        b.stop()


def test_a_killed_holder_frees_its_slot(tmp_path: Path) -> None:
    """The kernel drops a dead process's flock: a crashed calibrator never keeps a slot."""
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from ptz_selfcal.nodes.solve_slots import SolveSlots\n"
         "with SolveSlots(sys.argv[1], 1).hold() as held:\n    print(held, flush=True); time.sleep(60)",
         str(tmp_path)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "True"
        with SolveSlots(tmp_path, 1).hold() as held:
            assert not held
    finally:
        holder.kill()
        holder.wait()
    with SolveSlots(tmp_path, 1).hold() as held:
        assert held
