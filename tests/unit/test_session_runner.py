"""nodes/session_runner: a frame never waits for a solve, and a reset during a solve never publishes the
old reference's calibration. The solve waits on an event the test controls; the tests assert the order
of events, not times (the joins' timeouts only keep a regression from hanging the suite)."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from test_calibration_state import HEIGHT, WIDTH, encoded_sweep, feed

from ptz_selfcal.nodes.session_runner import RunnerConfig, SessionRunner
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameInput
from ptz_selfcal.online.session import CalibratorSession, Phase
from ptz_selfcal.online.work import WorkBatch, WorkResult
from ptz_selfcal.status import CALIBRATED, CalibrationStatus, TrackingState

SAFETY_S = 60.0  # a join that times out means the frame path waited for the solve: the test fails


class HeldSolve:
    """calibration.apply, held at its start until the test releases it; records the order of events."""

    def __init__(self, session: CalibratorSession) -> None:
        self.apply = session.calibration.apply
        self.started, self.release = threading.Event(), threading.Event()
        self.events: list[str] = []

    def __call__(self, work: WorkBatch, budget: float) -> WorkResult:
        if not work.keyframes:  # an idle wake-up: nothing to hold
            return self.apply(work, budget)
        self.started.set()
        self.release.wait(SAFETY_S)
        result = self.apply(work, budget)
        self.events.append("solve ended")
        return result


@pytest.fixture
def converged() -> tuple[CalibratorSession, np.ndarray, np.ndarray, np.ndarray]:
    """A session converged on a zooming sweep, with a usable zoom model (inline solves)."""
    K, H, f = encoded_sweep(120)
    session = CalibratorSession(SessionConfig(nominal_hfov_deg=50.0))
    feed(session, H, f)
    assert session.state == CalibrationStatus.CONVERGED
    return session, K, H, f


def start_held_solve(
    session: CalibratorSession, H: np.ndarray, f: np.ndarray
) -> tuple[SessionRunner, HeldSolve]:
    """A runner whose next solve (a new keyframe on the reference) is in progress and held."""
    held = HeldSolve(session)
    runner = SessionRunner(session, RunnerConfig(budget_s=5.0, period_s=0.01, save_period_s=1e9), solve=held)
    runner.start()
    frame = FrameInput(10.0, H[60], TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, 1000, "ref", float(f[60]))
    out, _ = runner.process(frame)
    assert out.status in CALIBRATED
    runner.wake()
    assert held.started.wait(SAFETY_S), "the worker never started the solve"
    return runner, held


def run_in_thread(fn, events: list[str], name: str):
    box = {}

    def target() -> None:
        box["out"] = fn()
        events.append(name)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    return thread, box


def test_a_frame_from_the_zoom_model_is_answered_while_a_solve_runs(converged) -> None:
    session, K, H, f = converged
    runner, held = start_held_solve(session, H, f)
    lost = FrameInput(11.0, None, TrackingState.TRACKING_LOST, WIDTH, HEIGHT, zoom=float(f[70]))
    thread, box = run_in_thread(lambda: runner.process(lost), held.events, "frame answered")
    thread.join(SAFETY_S)
    held.release.set()
    runner.stop()
    assert held.events == ["frame answered", "solve ended"]
    out, _ = box["out"]
    assert out.status == CalibrationStatus.PREDICTED_FROM_ZOOM and out.source == "zoom_model"
    assert abs(out.K[0, 0] / K[70][0, 0] - 1.0) < 0.02


def test_a_calibrated_frame_is_answered_while_a_solve_runs(converged) -> None:
    session, K, H, f = converged
    runner, held = start_held_solve(session, H, f)
    frame = FrameInput(11.0, H[61], TrackingState.TRACKING, WIDTH, HEIGHT, 1000, "ref", float(f[61]))
    thread, box = run_in_thread(lambda: runner.process(frame), held.events, "frame answered")
    thread.join(SAFETY_S)
    held.release.set()
    runner.stop()
    assert held.events == ["frame answered", "solve ended"]
    out, _ = box["out"]
    assert out.status == CalibrationStatus.CONVERGED and abs(out.K[1, 1] / K[61][1, 1] - 1.0) < 2e-3


def test_a_reset_during_a_solve_never_publishes_the_old_reference(converged) -> None:
    session, _, H, f = converged
    runner, held = start_held_solve(session, H, f)
    # the tracker starts a new map while the old reference's solve is in progress
    new_ref = FrameInput(
        11.0, np.eye(3), TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, 5000, "new_map", float(f[0])
    )
    out, _ = runner.process(new_ref)
    assert out.status == CalibrationStatus.INITIALISING
    held.release.set()
    # the held solve ends and its result (of the old reference) comes back; then the new map's frames
    runner.stop()
    assert held.events == ["solve ended"]
    assert session.snapshot is None or session.snapshot.epoch == session.take_work().epoch
    for j in (1, 2, 3):
        frame = FrameInput(
            11.0 + j, H[j], TrackingState.TRACKING, WIDTH, HEIGHT, 5000, "new_map", float(f[j])
        )
        out, _ = runner.process(frame)
        assert out.status not in CALIBRATED, (j, out.status, out.source)
        assert out.source != "calibration"


def test_the_session_phase_follows_its_events(converged) -> None:
    """NO_REFERENCE -> REFERENCED (a reference's first homography) -> CALIBRATED (a calibrated result)
    -> NO_REFERENCE (the reference changed); tracking lost changes no phase."""
    session, _, H, f = converged
    assert session.phase is Phase.CALIBRATED
    session.process(FrameInput(20.0, None, TrackingState.TRACKING_LOST, WIDTH, HEIGHT, zoom=float(f[5])))
    assert session.phase is Phase.CALIBRATED
    session.process(FrameInput(21.0, np.eye(3), TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, 7000, "other"))
    assert session.phase is Phase.REFERENCED  # the change reset it, the frame referenced the new map
    fresh = CalibratorSession(SessionConfig(nominal_hfov_deg=50.0))
    assert fresh.phase is Phase.NO_REFERENCE
    feed(fresh, H, f, frames=range(1))  # the reference alone: nothing to solve yet
    assert fresh.phase is Phase.REFERENCED
    feed(fresh, H, f, frames=range(1, 120))
    assert fresh.phase is Phase.CALIBRATED


def test_inline_solves_finish_before_the_next_frame() -> None:
    """inline_solves: no worker thread; the frame thread solves what the previous frames brought before
    it takes the next one, so a lock-step replay is the same every run."""
    _, H, f = encoded_sweep(120)
    session = CalibratorSession(
        SessionConfig(nominal_hfov_deg=50.0, min_solve_period_s=0.0, max_solve_duty=1.0)
    )
    runner = SessionRunner(session, RunnerConfig(budget_s=5.0, period_s=0.01, save_period_s=1e9))
    runner.start(inline=True)
    for j in range(0, 120, 8):
        runner.solve_inline()
        assert runner.pending == 0
        runner.process(
            FrameInput(j / 30.0, H[j], TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, j, "ref", float(f[j]))
        )
        assert runner.pending > 0  # collected, not solved: nothing runs behind the frame's back
    runner.solve_inline()
    assert session.counters["solves"] >= 2 and session.state in CALIBRATED
    runner.stop()


def test_a_failing_solve_is_counted_and_the_frames_go_on() -> None:
    """Inline or in the worker, an exception in a solve is logged and counted, never raised into the
    frame thread: the next frames are still answered."""
    _, H, f = encoded_sweep(120)
    session = CalibratorSession(
        SessionConfig(nominal_hfov_deg=50.0, min_solve_period_s=0.0, max_solve_duty=1.0)
    )
    logged: list[tuple[str, str]] = []

    def failing(work: WorkBatch, budget: float) -> WorkResult:
        raise RuntimeError("solver bug")

    runner = SessionRunner(
        session, RunnerConfig(5.0, 0.01, 1e9), log=lambda *entry: logged.append(entry), solve=failing
    )
    runner.start(inline=True)
    for j in (0, 8, 16):
        runner.solve_inline()
        out, _ = runner.process(
            FrameInput(j / 30, H[j], TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, j, "ref", f[j])
        )
        assert out.status == CalibrationStatus.INITIALISING
    assert runner.errors >= 2 and any("solver bug" in text for _, text in logged)
    runner.stop()
