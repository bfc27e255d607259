"""A reset (the calibrator's ~/reset) and a saved state of another camera, on the session and its runner:
a reset during a solve neither publishes nor saves what it dropped, and a restored state of another image
size gives way at the first frame. The solve waits on an event the test controls (test_session_runner's
HeldSolve): the tests assert the order of events, not times."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from test_calibration_state import HEIGHT, WIDTH, encoded_sweep, feed
from test_session_runner import SAFETY_S, HeldSolve

from ptz_selfcal.camera.geometry import intrinsic_matrix
from ptz_selfcal.nodes.session_runner import RunnerConfig, SessionRunner
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameInput
from ptz_selfcal.online.session import CalibratorSession
from ptz_selfcal.persist.state_files import STATE_FILE, ZOOM_MODEL_FILE
from ptz_selfcal.status import CALIBRATED, CalibrationStatus, TrackingState


def converged(state_dir: Path) -> tuple[CalibratorSession, np.ndarray, np.ndarray]:
    """A session converged on a zooming sweep with a usable zoom model, saved in state_dir."""
    _, H, f = encoded_sweep(120)
    session = CalibratorSession(SessionConfig(nominal_hfov_deg=50.0), state_dir=state_dir)
    feed(session, H, f)
    assert session.state == CalibrationStatus.CONVERGED
    session.save()
    assert (state_dir / STATE_FILE).exists() and (state_dir / ZOOM_MODEL_FILE).exists()
    return session, H, f


def test_a_reset_during_a_solve_keeps_nothing_of_it(tmp_path: Path) -> None:
    session, H, f = converged(tmp_path)
    held = HeldSolve(session)
    runner = SessionRunner(session, RunnerConfig(budget_s=5.0, period_s=0.01, save_period_s=0.0), solve=held)
    runner.start()
    try:
        frame = FrameInput(10.0, H[60], TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, 1000, "ref", float(f[60]))
        assert runner.process(frame)[0].status in CALIBRATED
        runner.wake()
        assert held.started.wait(SAFETY_S)  # the solve of the old calibration is in progress
        removed = runner.reset("reset requested")
        assert sorted(p.name for p in removed) == sorted([STATE_FILE, ZOOM_MODEL_FILE])
        lost = FrameInput(11.0, None, TrackingState.TRACKING_LOST, WIDTH, HEIGHT, zoom=float(f[70]))
        out, _ = runner.process(lost)  # no zoom model, no last good K: the nominal prior
        assert out.status == CalibrationStatus.TRACKING_LOST and out.source == "nominal"
        held.release.set()
        runner.wake()
        deadline = time.monotonic() + SAFETY_S
        while runner.pending and time.monotonic() < deadline:
            time.sleep(0.01)
        assert runner.pending == 0
        snap = session.snapshot  # the old epoch's result was dropped: at most the new epoch's empty one
        assert snap is None or (snap.epoch == 1 and not snap.calibrated and snap.keyframe_count == 1), snap
        assert runner.save() == []  # nothing learned since: the deleted files stay the state
        assert not any((tmp_path / name).exists() for name in (STATE_FILE, ZOOM_MODEL_FILE))
        calibrator = session.calibration.calibrator
        assert session.calibration.zoom_model.is_empty()
        assert calibrator is None or (not calibrator.calibrated and not calibrator.keyframes)
        out, _ = runner.process(lost)
        assert out.source == "nominal"
    finally:
        held.release.set()
        runner.stop()
    # the frames that come after it are a new reference: saved as a fresh state
    assert (tmp_path / STATE_FILE).exists() is False
    out, _ = runner.process(FrameInput(12.0, np.eye(3), TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, 0, "new"))
    assert out.status == CalibrationStatus.INITIALISING
    assert runner.save() and (tmp_path / STATE_FILE).exists()


def test_a_saved_state_of_another_image_size_gives_way_at_the_first_frame(tmp_path: Path) -> None:
    converged(tmp_path)
    session = CalibratorSession(SessionConfig(nominal_hfov_deg=50.0), state_dir=tmp_path)
    assert any(line.startswith("restored calibration state") for line in session.restore())
    assert session.state in CALIBRATED
    width, height = WIDTH // 2, HEIGHT // 2
    frame = FrameInput(1.0, np.eye(3), TrackingState.NEW_KEYFRAME, width, height, 0, "ref", 300.0)
    out = session.process(frame)
    stale = session.take_stale_state()
    assert stale and f"{WIDTH}x{HEIGHT}" in stale and f"{width}x{height}" in stale
    f_nominal = 0.5 * width / math.tan(math.radians(25.0))
    np.testing.assert_allclose(out.K, intrinsic_matrix(f_nominal, 0.5 * (width - 1), 0.5 * (height - 1)))
    assert out.status == CalibrationStatus.INITIALISING and session.counters["resets"] == 1
    session.step(1.0, paced=False)  # inline, the solving half forgets too: no zoom model of that camera
    assert session.calibration.zoom_model.is_empty()
    assert session.snapshot is not None and session.snapshot.calibrator.image_size == (width, height)
