"""A reset (the calibrator's ~/reset) and a saved state of another camera, on the session and its runner:
a reset during a solve neither publishes nor saves what it dropped, and a restored state of another image
size gives way at the first frame. The solve waits on an event the test controls (test_session_runner's
HeldSolve): the tests assert the order of events, not times."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
from test_calibration_state import HEIGHT, WIDTH, encoded_sweep, feed, zoom_counts
from test_session_runner import SAFETY_S, HeldSolve

from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation
from ptz_selfcal.nodes.session_runner import RunnerConfig, SessionRunner
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameInput
from ptz_selfcal.online.gates import RestoredStateCheck
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


def _still_zoom_pan(session: CalibratorSession, scale: float, frames: int = 40) -> list:
    """Frames of a pan at a still zoom (f 1500 px of the saved lens), tracked against the saved reference,
    through a lens whose f is `scale` times the saved lens's at that zoom encoder reading: a lens swapped
    at the same image size (scale 1: the same lens)."""
    K_old_ref = intrinsic_matrix(1000.0, 639.5 + 15.0, 359.5 - 10.0)  # the saved sweep's reference K
    assert np.allclose(session.snapshot.calibrator.reference_K, K_old_ref, rtol=5e-3)
    K = intrinsic_matrix(1500.0 * scale, 639.5 + 15.0, 359.5 - 10.0)
    zoom = float(zoom_counts(1500.0)[0])
    outs = []
    for j in range(frames):
        pan, tilt = np.radians(3.0 * np.sin(j / 10.0)), np.radians(1.0 * np.cos(j / 7.0))
        H = K @ ptz_rotation(pan, tilt) @ np.linalg.inv(K_old_ref)
        frame = FrameInput(100.0 + j / 30.0, H, TrackingState.TRACKING, WIDTH, HEIGHT, 0, "ref", zoom)
        outs.append(session.process(frame))
    return outs


# 0.92: within the zoom gate's floor (one frame passes it), beyond 4 sigma of the saved model
@pytest.mark.parametrize("scale", [1.25, 0.92])
def test_a_saved_state_of_another_lens_of_the_same_image_size_gives_way(tmp_path: Path, scale: float) -> None:
    """A lens swapped at the same image size: the frames' focal lengths through their homographies
    (eq. 20) disagree with the saved zoom model at their zoom encoder; within the first frames judged
    the session starts fresh with a warning, and no later frame is served from the old lens's model."""
    converged(tmp_path)
    session = CalibratorSession(SessionConfig(nominal_hfov_deg=50.0), state_dir=tmp_path)
    session.restore()
    outs = _still_zoom_pan(session, scale)
    stale = session.take_stale_state()
    assert stale and "swapped camera or lens" in stale and "disagree with the saved zoom model" in stale
    assert session.counters["resets"] == 1
    first = next(j for j, out in enumerate(outs) if out.status == CalibrationStatus.INITIALISING)
    assert first <= RestoredStateCheck.FRAMES + 1
    for out in outs[first:]:  # the nominal prior through the frame's homography, not the old zoom model
        assert out.status == CalibrationStatus.INITIALISING and out.source in ("prior", "nominal"), out
    session.step(1.0, paced=False)
    assert session.calibration.zoom_model.is_empty()


def test_a_saved_state_of_the_same_lens_is_kept(tmp_path: Path) -> None:
    """The control: the same lens after a restart keeps its calibration and zoom model."""
    converged(tmp_path)
    session = CalibratorSession(SessionConfig(nominal_hfov_deg=50.0), state_dir=tmp_path)
    session.restore()
    outs = _still_zoom_pan(session, 1.0)
    assert session.take_stale_state() is None and session.counters["resets"] == 0
    assert session.calibration.zoom_model.sample_count > 0
    for out in outs:
        assert out.status in CALIBRATED, out
        assert abs(out.K[1, 1] / 1500.0 - 1.0) < 0.01, out.K


def test_a_fresh_tracker_under_the_saved_reference_name_restarts_the_calibration(tmp_path: Path) -> None:
    """A tracker without the saved map that names its reference and keyframes as the saved ones (the same
    first stamp): a saved keyframe id re-announced with the saved homography changes nothing, with
    another homography it restarts the calibration on the tracker's reference, and the frames are judged
    against the saved zoom model again."""
    _, H, f = converged(tmp_path)
    session = CalibratorSession(SessionConfig(nominal_hfov_deg=50.0), state_dir=tmp_path)
    session.restore()
    saved = session.snapshot.keyframes
    kid = next(k for k in sorted(saved) if k > 0)
    again = FrameInput(
        50.0, saved[kid][0], TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, kid, "ref", float(f[kid])
    )
    assert session.process(again).status in CALIBRATED
    assert session.counters["reference_changes"] == 0
    other = FrameInput(
        51.0, H[kid + 3], TrackingState.NEW_KEYFRAME, WIDTH, HEIGHT, kid, "ref", float(f[kid + 3])
    )
    out = session.process(other)
    assert session.counters["reference_changes"] == 1 and out.status == CalibrationStatus.INITIALISING
    assert any("is not the saved one" in w for w in session.take_warnings())
    assert session.take_stale_state() is None and session.calibration.zoom_model.sample_count > 0
