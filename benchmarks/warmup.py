"""Issue 15: how soon the session calibrates, and how well, on small and slow motions (in process).

Each family's true camera (sim/render.CameraProfile) is tracked as a keyframe tracker would
(sim/tracked.tracked_frames: every frame's homography through its keyframe, keyframe matches) and fed
frame by frame to online/session.CalibratorSession with the shipped defaults, its solves run inline
and unpaced as in `ptz-selfcal run --deterministic`. Printed per family and seed: the well-posed
frame (2 deg about each of two axes from the first frame), the first calibrated frame (CALIBRATING or
CONVERGED), the focal error median / p90 after max(10 % of frames, well-posed + 1 s), and the CONVERGED
frames more than 1 % off.

    ros2_ws/venv/bin/python benchmarks/warmup.py [--seeds 0 1 2] [--families paperA longfocal]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from ptz_selfcal.online.session import CalibratorSession, FrameInput, SessionConfig
from ptz_selfcal.sim.metrics import well_posed_frame
from ptz_selfcal.sim.render import CameraProfile, focal_from_hfov
from ptz_selfcal.sim.tracked import profile_truth, tracked_frames
from ptz_selfcal.status import CALIBRATED, CalibrationStatus, TrackingState


def families() -> dict[str, tuple[CameraProfile, int, float]]:
    """name -> (profile, frames, fps)."""
    circle = {"motion": "circle", "zoom_law": "linear", "pp_offset": (0.0, 0.0)}
    return {
        # section 4.1: 30 frames of 640x480 at 2 fps, configurations A and B
        "paperA": (
            CameraProfile(640, 480, 29 / 2.0, 800.0, 1400 / 800, circle_radius=np.radians(5.0), **circle),
            30,
            2.0,
        ),
        "paperB": (
            CameraProfile(640, 480, 29 / 2.0, 1200.0, 2000 / 1200, circle_radius=np.radians(3.5), **circle),
            30,
            2.0,
        ),
        "longfocal": (
            CameraProfile(
                1280,
                720,
                149 / 30.0,
                2500.0,
                4200 / 2500,
                circle_radius=np.radians(3.0),
                motion="circle",
                zoom_law="linear",
            ),
            150,
            30.0,
        ),
        "sweep720": (CameraProfile(1280, 720, 299 / 30.0, focal_from_hfov(1280, 54.0)), 300, 30.0),
    }


def replay(session: CalibratorSession, profile: CameraProfile, n: int, fps: float, seed: int) -> tuple:
    """Feed the tracked family to the session; (outputs, true K, true R)."""
    K, R = profile_truth(profile, n, fps)
    frames = tracked_frames(K, R, (profile.width, profile.height), seed=seed)
    outs = []
    for tf in frames:
        state = TrackingState.NEW_KEYFRAME if tf.new_keyframe else TrackingState.TRACKING
        f_true = K[tf.index][1, 1]
        frame = FrameInput(
            tf.index / fps,
            tf.H,
            state,
            profile.width,
            profile.height,
            tf.keyframe_id,
            "ref",
            zoom=1000.0 * math.log(f_true),
        )
        outs.append(session.process(frame))
        if tf.matches is not None:
            a, b, pa, pb = tf.matches
            session.add_keyframe_matches(a, b, pa, pb)
        for _ in range(3):  # as solve_inline: unpaced, a first solve asks for a refinement
            if not session.pending_work:
                break
            session.accept(session.calibration.apply(session.take_work(paced=False), 5.0))
    return outs, K, R


def measure(name: str, seed: int) -> dict:
    profile, n, fps = families()[name]
    session = CalibratorSession(SessionConfig())
    t0 = time.perf_counter()
    outs, K, R = replay(session, profile, n, fps, seed)
    seconds = time.perf_counter() - t0
    f_true = K[:, 1, 1]
    f = np.array([o.K[1, 1] for o in outs])
    err = np.abs(f / f_true - 1.0)
    status = [o.status for o in outs]
    calibrated = [j for j, s in enumerate(status) if s in CALIBRATED]
    posed = well_posed_frame(R)
    start = max(math.ceil(0.1 * n), (posed if posed is not None else n) + round(fps))
    late = err[start:]
    converged = np.array([s == CalibrationStatus.CONVERGED for s in status])
    return {
        "family": name,
        "seed": seed,
        "frames": n,
        "well_posed": posed,
        "first_calibrated": calibrated[0] if calibrated else None,
        "target": None if posed is None else posed + max(round(fps), 3),
        "median_pct": 100 * float(np.median(late)) if late.size else math.nan,
        "p90_pct": 100 * float(np.percentile(late, 90)) if late.size else math.nan,
        "converged": int(converged.sum()),
        "converged_off": int(np.sum(converged & (err > 0.01))),
        "keyframes": session.counters["keyframes"],
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--families", nargs="+", default=list(families()))
    args = parser.parse_args()
    print(
        f"{'family':<10} {'seed':>4} {'posed':>5} {'first':>5} {'target':>6} {'med%':>7} {'p90%':>7} "
        f"{'conv':>5} {'off':>4} {'kf':>4} {'s':>6}"
    )
    for name in args.families:
        for seed in args.seeds:
            r = measure(name, seed)
            print(
                f"{name:<10} {seed:>4} {r['well_posed']!s:>5} {r['first_calibrated']!s:>5} "
                f"{r['target']!s:>6} "
                f"{r['median_pct']:>7.3f} {r['p90_pct']:>7.3f} {r['converged']:>5} {r['converged_off']:>4} "
                f"{r['keyframes']:>4} {r['seconds']:>6.1f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
