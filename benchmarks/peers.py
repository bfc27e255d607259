"""Side by side with the peers (issue 8): ptz_selfcal against OpenCV's stitching calibration and the paper.

    ros2_ws/venv/bin/python benchmarks/peers.py [--quick] [--inputs clean,distorted,...] [--out FILE]

Inputs: `ptz-selfcal synth` bags rendered on the fly from /work/shared/data/panoramas into a temporary
directory (clean; radial distortion; long focal length with small rotations, the near-ambiguity case of
section 6.2) and the real hand-held sets of /work/shared/data/rotation_sets (focal length compared with
AutoStitch's, full-resolution f = s * f). OpenCV sees every 5th frame; ptz_selfcal's online row sees
every frame one by one; the errors of every row are measured on the same frames (every 5th).

Rows per input: OpenCV's stitching pipeline (benchmarks/opencv_peer.py) and its two autocalib helpers
(ported / corrected) on the tracker's homographies; the paper's methods on the tracker's homographies
(linear square pixels with the principal point known = image centre and varying; LM eq. 22 with a
constant and a varying principal point; bundle adjustment MLE eq. 26 and MAP eq. 27 on points
transferred by those homographies); ptz_selfcal online (the tracker + the calibrator node's
CalibratorSession with its defaults, a zooming camera) and, on the real sets, the same session with
focal_model "constant" (a fixed lens), with and without estimate_distortion. "As published" counts the
frames the session published as CONVERGED; "final state" replays every frame through the calibration
the session held at the end.
"""

from __future__ import annotations

import os

# One BLAS thread, as in the product's processes (ptz_selfcal/__init__.py sets it before numpy loads;
# here numpy loads first): a multi-threaded OpenBLAS spin-waits on the small systems of the keyframe
# adjustment and counted 2-4x the calibration's single-threaded CPU per still on this 2-core machine.
# OpenCV's own thread pool is not BLAS: its row is unchanged.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parent))

import opencv_peer

from ptz_selfcal.camera.intrinsics import (
    IntrinsicsModel,
    ParamMode,
    SelfCalibrationError,
    image_centre,
    rotations_from_homographies,
)
from ptz_selfcal.frontend.stills import StillsConfig, StillsTracker
from ptz_selfcal.frontend.tracker import (
    HomographyTracker,
)
from ptz_selfcal.sim import metrics
from ptz_selfcal.status import HOMOGRAPHY_STATES, CalibrationStatus

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]

DATA = Path("/work/shared/data")
STRIDE = 5  # OpenCV sees every 5th frame (issue 8)
FPS = 15.0
SESSION_BUDGET_S = 0.5  # the calibrator node's default reoptimise_budget
# A fixed lens (the real sets): constant unknown focal length and principal point, square pixels.
FIXED_LENS = IntrinsicsModel(focal=ParamMode.CONSTANT)
RESULTS = Path(__file__).resolve().parent / "results" / "peers.txt"


# --------------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------------
@dataclass
class Sequence:
    """Frames (mono8, full resolution) and what is known about them."""

    name: str
    frames: list[np.ndarray]
    eval_idx: IntArray  # frames every method is evaluated on (and OpenCV is fed)
    K_true: Array | None = None  # (n, 3, 3)
    R_true: Array | None = None  # (n, 3, 3) world-to-camera
    f_reference: float | None = None  # AutoStitch's focal length (real sets)
    source: str = ""
    fixed_focal: bool = False  # a fixed lens: photographs, not video (real sets)
    distorted: bool = False  # radial distortion in the images (synthetic inputs)

    @property
    def size(self) -> tuple[int, int]:
        h, w = self.frames[0].shape[:2]
        return (w, h)


@dataclass(frozen=True)
class SynthSpec:
    panorama: str
    hfov_deg: float  # at the wide end
    zoom_max: float
    pan_deg: float
    tilt_deg: float
    distortion: float = 0.0  # corner shift, fraction of the half-diagonal at the wide end
    width: int = 1280
    height: int = 720


SYNTH: dict[str, SynthSpec] = {
    "clean": SynthSpec("building.jpg", 60.0, 2.0, 30.0, 8.0),
    "distorted": SynthSpec("building.jpg", 60.0, 2.0, 30.0, 8.0, distortion=0.12),
    "longfocal": SynthSpec("building.jpg", 30.0, 1.6, 3.5, 2.0),
}
REAL = ("parrington", "grail", "denny", "weir")


def _gray(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def render_sequence(name: str, spec: SynthSpec, n_frames: int, fps: float = FPS) -> Sequence:
    """Render in-process with sim.render (used when the synth command is not installed)."""
    from ptz_selfcal.sim import render

    pano = render.build_panorama(cv2.imread(str(DATA / "panoramas" / spec.panorama), cv2.IMREAD_GRAYSCALE))
    profile = render.CameraProfile(
        spec.width,
        spec.height,
        period=n_frames / fps,
        f_wide=render.focal_from_hfov(spec.width, spec.hfov_deg),
        zoom_max=spec.zoom_max,
        pan_amplitude=np.radians(spec.pan_deg),
        tilt_amplitude=np.radians(spec.tilt_deg),
        corner_shift=spec.distortion,
    )
    state = profile.state(np.arange(n_frames) / fps)
    size = (spec.width, spec.height)
    frames = [
        render.render_view(pano, state.K(i), state.R(i), size, float(state.lam[i]) or None)
        for i in range(n_frames)
    ]
    K = np.array([state.K(i) for i in range(n_frames)])
    R = np.array([state.R(i) for i in range(n_frames)])
    source = "sim.render (in-process)"
    return Sequence(
        name, frames, np.arange(0, n_frames, STRIDE), K, R, source=source, distorted=spec.distortion > 0
    )


def load_real_set(name: str) -> Sequence:
    """A rotation set with AutoStitch's focal length (mean of its per-image full-resolution f)."""
    folder = DATA / "rotation_sets" / name
    paths = sorted(p for p in folder.glob("*.jpg"))
    frames = [_gray(cv2.imread(str(p))) for p in paths]
    ref = autostitch_focal(folder)
    source = (
        f"real hand-held photographs, AutoStitch f = {ref:.1f} px" if ref else "real hand-held photographs"
    )
    return Sequence(name, frames, np.arange(len(frames)), f_reference=ref, source=source, fixed_focal=True)


def autostitch_focal(folder: Path) -> float | None:
    """Mean full-resolution f = s * f over the images of autostitch_pano.txt (None without the file)."""
    path = folder / "autostitch_pano.txt"
    if not path.exists():
        return None
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    focals = []
    # Blocks of 9 non-empty lines: path, "w h", 3 rows of the scale matrix, 3 rows of R, f.
    for k in range(0, len(lines) - 8, 9):
        scale = float(lines[k + 2][0])
        focals.append(scale * float(lines[k + 8][0]))
    return float(np.mean(focals)) if focals else None


def autostitch_rotations(folder: Path) -> Array | None:
    """AutoStitch's (n, 3, 3) R of each image of autostitch_pano.txt, in file order (None without it)."""
    path = folder / "autostitch_pano.txt"
    if not path.exists():
        return None
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    blocks = range(0, len(lines) - 8, 9)  # as autostitch_focal: rows 5-7 of a block are R
    return np.array([[[float(x) for x in lines[k + r]] for r in (5, 6, 7)] for k in blocks])


# --------------------------------------------------------------------------------------------------
# Method results
# --------------------------------------------------------------------------------------------------
@dataclass
class MethodResult:
    method: str
    online: bool
    frame_idx: IntArray  # sequence frames with an estimate
    K: Array  # (m, 3, 3)
    R: Array  # (m, 3, 3), any common gauge
    ms_per_frame: float  # wall time
    note: str = ""
    extra: dict = field(default_factory=dict)
    cpu_ms_per_frame: float = float("nan")  # process CPU time


def failed(method: str, online: bool, note: str) -> MethodResult:
    empty = np.empty((0, 3, 3))
    return MethodResult(method, online, np.zeros(0, np.intp), empty, empty, float("nan"), note)


# --------------------------------------------------------------------------------------------------
# OpenCV
# --------------------------------------------------------------------------------------------------
def run_opencv(seq: Sequence, features: str, cache: Path | None = None) -> MethodResult:
    """OpenCV's pipeline on the evaluation frames. With `cache`, a result stored by an earlier run on
    byte-identical images and the same configuration is reused (its measured times included, and the
    row says when it was measured): OpenCV's side does not change when ptz_selfcal does."""
    images = [seq.frames[i] for i in seq.eval_idx]
    config = opencv_peer.OpenCVConfig(features=features)
    name = f"OpenCV stitching ({features.upper()}, Ray+Reproj BA)"
    path = None if cache is None else cache / f"{seq.name}_{opencv_cache_key(images, config)}.npz"
    note = ""
    if path is not None and path.exists():
        res, note = load_opencv_result(path)
    else:
        load = os.getloadavg()[0]
        res = opencv_peer.run_stitching_calibration(images, config)
        if path is not None:
            save_opencv_result(path, res, load)
    if not res.ok:
        return failed(name, False, res.message)
    ms = 1000.0 * res.wall_time / len(images)
    cpu = 1000.0 * res.cpu_time / len(images)
    return MethodResult(name, False, seq.eval_idx[res.indices], res.K, res.R, ms, note, res.stage_times, cpu)


def opencv_cache_key(images: list[np.ndarray], config: opencv_peer.OpenCVConfig) -> str:
    """Digest of the images' pixels and the OpenCV configuration (and OpenCV's version)."""
    digest = hashlib.sha256(repr((config, cv2.__version__)).encode())
    for image in images:
        digest.update(repr(image.shape).encode())
        digest.update(np.ascontiguousarray(image).tobytes())
    return digest.hexdigest()[:16]


def save_opencv_result(path: Path, res: opencv_peer.OpenCVResult, load: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    meta = {"ok": res.ok, "message": res.message, "stage_times": res.stage_times, "measured": stamp}
    meta |= {"wall_time": res.wall_time, "cpu_time": res.cpu_time, "load": load}
    with open(path, "wb") as fh:
        np.savez(fh, indices=res.indices, K=res.K, R=res.R, meta=json.dumps(meta))


def load_opencv_result(path: Path) -> tuple[opencv_peer.OpenCVResult, str]:
    with np.load(path) as data:
        meta = json.loads(str(data["meta"]))
        res = opencv_peer.OpenCVResult(
            data["indices"], data["K"], data["R"], meta["wall_time"], meta["cpu_time"], meta["ok"],
            meta["message"], meta["stage_times"],
        )  # fmt: skip
    return res, f"measured {meta['measured']} (load at start {meta['load']:.1f}), reused"


# --------------------------------------------------------------------------------------------------
# ptz_selfcal: tracking (shared by the paper rows and the online row)
# --------------------------------------------------------------------------------------------------
@dataclass
class Tracking:
    H_ref: list[Array | None]  # per frame: reference -> frame, full resolution (None when lost)
    reference_id: list[int | None]
    seconds: float
    results: list = field(default_factory=list)
    cpu_seconds: float = float("nan")
    stage_cpu: dict[str, float] = field(default_factory=dict)  # StillsTracker's CPU seconds per stage


def working_scale(size: tuple[int, int]) -> float:
    """The node's working resolution: about 640 pixels wide."""
    return min(1.0, 640.0 / size[0])


def to_working(image: np.ndarray, scale: float) -> np.ndarray:
    if scale == 1.0:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)


def track_sequence(
    seq: Sequence, on_frame: Callable | None = None, stills: StillsConfig | None = None
) -> Tracking:
    """Feed every frame to the tracker; on_frame(i, image, scale, result) runs inside the timing. The
    real sets (stills) go through frontend/stills.StillsTracker (`stills`: its configuration, default its
    defaults), video through HomographyTracker."""
    tracker = StillsTracker(stills or StillsConfig()) if seq.fixed_focal else HomographyTracker()
    scale = working_scale(seq.size)
    H_ref: list[Array | None] = []
    refs: list[int | None] = []
    results = []
    t0 = time.perf_counter()
    c0 = time.process_time()
    for i, frame in enumerate(seq.frames):
        work = to_working(frame, scale)
        result = tracker.track(work, scale, i / FPS)
        H_ref.append(result.H_ref)
        refs.append(result.reference_id)
        results.append(result)
        if on_frame is not None:
            on_frame(i, frame, scale, result)
    stages = dict(getattr(tracker, "cpu", {}))
    return Tracking(H_ref, refs, time.perf_counter() - t0, results, time.process_time() - c0, stages)


def homographies_at(seq: Sequence, tracking: Tracking) -> tuple[IntArray, Array]:
    """Evaluation frames tracked against the first map's reference, and their H (reference -> frame).

    The reference frame itself is prepended when it is not an evaluation frame (H = I).
    """
    first = next((r for r in tracking.reference_id if r is not None), None)
    keep = [i for i in seq.eval_idx if tracking.H_ref[i] is not None and tracking.reference_id[i] == first]
    if first is not None and first not in keep:
        keep = [first, *keep]
    idx = np.array(sorted(keep), dtype=np.intp)
    H = np.array([tracking.H_ref[i] for i in idx]) if len(idx) else np.empty((0, 3, 3))
    order = np.argsort(idx != first, kind="stable")  # reference first: the solvers expect H[0] = I
    H = H[order]
    return idx[order], H / np.cbrt(np.linalg.det(H))[:, None, None]  # unit det (H[2, 2] may be ~0)


# --------------------------------------------------------------------------------------------------
# Rows on the tracker's homographies
# --------------------------------------------------------------------------------------------------
def _timed(fn: Callable[[], tuple[Array, Array]]) -> tuple[Array, Array, float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    K, R = fn()
    return K, R, time.perf_counter() - t0, time.process_time() - c0


def centred(H: Array, size: tuple[int, int]) -> Array:
    """Homographies in coordinates centred on the image centre (OpenCV's matcher convention)."""
    cx, cy = image_centre(size)
    T = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    return T @ H @ np.linalg.inv(T)


def opencv_focals_from_homography(H: Array, size: tuple[int, int]) -> tuple[Array, Array]:
    """Per-frame K from the ported focalsFromHomography (f1 of ref -> frame j; pp = centre)."""
    cx, cy = image_centre(size)
    f = np.full(len(H), np.nan)
    f_ref = []
    for j, Hc in enumerate(centred(H, size)):
        f0, f1, ok0, ok1 = opencv_peer.focals_from_homography(Hc)
        if ok1:
            f[j] = f1
        if ok0:
            f_ref.append(f0)
    if not f_ref:
        raise SelfCalibrationError("focalsFromHomography found no focal length")
    f[0] = np.median(f_ref)
    if not np.isfinite(f).all():
        raise SelfCalibrationError(f"focalsFromHomography failed on {int((~np.isfinite(f)).sum())} frames")
    K = np.array([[[fj, 0.0, cx], [0.0, fj, cy], [0.0, 0.0, 1.0]] for fj in f])
    return K, rotations_from_homographies(H, K)


def opencv_calibrate_rotating(H: Array) -> tuple[Array, Array]:
    """Constant K from cv2.detail.calibrateRotatingCamera with the Cholesky correction."""
    K = opencv_peer.calibrate_rotating_camera_binding(list(H[1:]))
    if K is None:
        raise SelfCalibrationError("calibrateRotatingCamera failed (W not positive definite)")
    Ks = np.repeat(K[None], len(H), axis=0)
    return Ks, rotations_from_homographies(H, Ks)


def transferred_observations(
    H: Array, size: tuple[int, int], grid: int = 12
) -> tuple[IntArray, IntArray, Array]:
    """BA observations: a grid of every frame mapped into every other frame by the homographies.

    A grid point is a ray; it is observed in its own frame and wherever it lands inside another image.
    """
    from ptz_selfcal.camera.geometry import pixel_grid

    w, h = size
    g = pixel_grid(w, h, grid)
    n, m = len(H), len(g)
    Hinv = np.linalg.inv(H)
    frames, rays, xys = [], [], []
    for a in range(n):
        M = H @ Hinv[a]  # frame a -> every frame
        p = np.einsum("nij,mj->nmi", M, np.column_stack([g, np.ones(m)]))
        xy = p[..., :2] / p[..., 2:3]
        inside = (p[..., 2] > 0) & (xy[..., 0] >= 0) & (xy[..., 0] <= w - 1) & (xy[..., 1] >= 0)
        inside &= xy[..., 1] <= h - 1
        fb, pt = np.nonzero(inside)
        frames.append(fb)
        rays.append(a * m + pt)
        xys.append(xy[fb, pt])
    return np.concatenate(frames), np.concatenate(rays), np.concatenate(xys)


def link_observations(tracking: Tracking, idx: IntArray) -> tuple[IntArray, IntArray, Array]:
    """BA observations from the tracker's keyframe links between evaluation frames (real measurements)."""
    from ptz_selfcal.bundle import pair_observations

    pos = {int(f): k for k, f in enumerate(idx)}
    links = {(lk.source_id, lk.target_id): lk for r in tracking.results for lk in r.links}
    matches = [
        (pos[s], pos[t], lk.source_points, lk.target_points)
        for (s, t), lk in links.items()
        if s in pos and t in pos
    ]
    obs = pair_observations(matches)
    return obs.frame_idx, obs.ray_idx, obs.xy


def bundle_rows(
    obs: tuple, size: tuple[int, int], inits: dict[str, tuple[Array, Array]]
) -> dict[str, Callable]:
    """MLE (eq. 26) and MAP (eq. 27) from the LM solutions; a fixed lens gets its own MAP row."""
    from ptz_selfcal.bundle import bundle_adjust, default_pp_prior

    def run(model: IntrinsicsModel, init: tuple[Array, Array], prior=None) -> Callable:
        def fn() -> tuple[Array, Array]:
            r = bundle_adjust(obs, init[0], init[1], size, model, pp_prior=prior, max_iterations=100)
            return r.K, r.R

        return fn

    rows = {}
    if "const" in inits:
        rows["BA MLE eq.26 (const pp)"] = run(IntrinsicsModel.square_constant_pp(), inits["const"])
        prior = default_pp_prior(size)
        rows["BA MAP eq.27 (varying pp, prior)"] = run(
            IntrinsicsModel.square_varying_pp(), inits["const"], prior
        )
    if "fixed" in inits:
        rows["BA MAP eq.27 (const f+pp, fixed lens)"] = run(
            FIXED_LENS, inits["fixed"], default_pp_prior(size)
        )
    return rows


def paper_rows(seq: Sequence, tracking: Tracking) -> list[MethodResult]:
    """The paper's methods and OpenCV's autocalib helpers on the same (tracked) homographies."""
    from ptz_selfcal.selfcal.linear import linear_selfcalibration
    from ptz_selfcal.selfcal.lm import lm_selfcalibration

    idx, H = homographies_at(seq, tracking)
    size = seq.size
    track_ms = (1000.0 * tracking.seconds / len(seq.frames), 1000.0 * tracking.cpu_seconds / len(seq.frames))
    if len(idx) < 3:
        return [failed("paper methods", False, f"only {len(idx)} tracked evaluation frames")]

    def lin(known: bool) -> Callable:
        def fn() -> tuple[Array, Array]:
            r = linear_selfcalibration(H, size, known_principal_point=image_centre(size) if known else None)
            return r.K, r.R

        return fn

    notes: dict[str, str] = {}

    def lm(name: str, model: IntrinsicsModel) -> tuple[str, Callable]:
        def fn() -> tuple[Array, Array]:
            r = lm_selfcalibration(H, size, model)
            if not r.ok:  # a collapse of f is a failure; a motion flag (section 6) is reported
                if r.motion is None or r.motion.well_posed:
                    raise SelfCalibrationError(r.message)
                notes[name] = f"flagged: {r.motion.status}"
            return r.K, r.R

        return name, fn

    methods: dict[str, Callable] = {
        "OpenCV focalsFromHomography (ported)": lambda: opencv_focals_from_homography(H, size),
        "OpenCV calibrateRotatingCamera (corr.)": lambda: opencv_calibrate_rotating(H),
        "linear sq.px, known pp=centre (3.3.2)": lin(True),
        "linear sq.px, varying pp (3.3.2)": lin(False),
    }
    lm_models = [
        ("LM eq.22, constant pp (3.3.1)", IntrinsicsModel.square_constant_pp()),
        ("LM eq.22, varying pp (3.3.1)", IntrinsicsModel.square_varying_pp()),
    ]
    if seq.fixed_focal:
        lm_models.append(("LM eq.22, constant f+pp (fixed lens)", FIXED_LENS))
    methods |= dict(lm(name, model) for name, model in lm_models)
    rows = []
    inits: dict[str, tuple[Array, Array]] = {}
    for name, fn in methods.items():
        rows.append(_solve_row(name, fn, idx, track_ms))
        rows[-1].note = rows[-1].note or notes.get(name, "")
        if name.startswith("LM eq.22, constant") and len(rows[-1].frame_idx):
            inits["fixed" if "fixed" in name else "const"] = (rows[-1].K, rows[-1].R)
    if not inits:
        return [*rows, failed("BA MLE / MAP", False, "no LM initialisation")]
    # Real sets: the links' own matches (every image is a keyframe); video: points transferred by H.
    obs = link_observations(tracking, idx) if seq.fixed_focal else transferred_observations(H, size)
    for name, fn in bundle_rows(obs, size, inits).items():
        rows.append(_solve_row(name, fn, idx, track_ms))
        rows[-1].note = rows[-1].note or ("link matches" if seq.fixed_focal else "points transferred by H")
    return rows


def _solve_row(name: str, fn: Callable, idx: IntArray, track_ms: tuple[float, float]) -> MethodResult:
    try:
        K, R, seconds, cpu = _timed(fn)
    except (SelfCalibrationError, np.linalg.LinAlgError, ValueError) as exc:
        return failed(name, False, str(exc).splitlines()[0][:60])
    ms = track_ms[0] + 1000.0 * seconds / len(idx)
    return MethodResult(name, False, idx, K, R, ms, cpu_ms_per_frame=track_ms[1] + 1000.0 * cpu / len(idx))


# --------------------------------------------------------------------------------------------------
# ptz_selfcal online
# --------------------------------------------------------------------------------------------------
# The real sets are still photographs without time stamps: the session gets one still per second (a
# hand-held pan), not the video rate, so its fast-motion gate (SessionConfig.max_keyframe_motion, image
# widths per second) judges them as a photographer's pace rather than as a preset recall at 15 fps.
STILL_INTERVAL_S = 1.0
ONLINE = "ptz_selfcal online (nodes' tracker+calibrator)"


def session_config(focal_model: str = "varying", fixed_lens_distortion: bool = False):
    """The calibrator node's configuration: its defaults, and focal_model / estimate_distortion as the
    node passes them (a fixed lens estimates its one distortion coefficient in the session)."""
    from ptz_selfcal.online.session import SessionConfig

    return SessionConfig(
        focal_model=focal_model,
        estimate_distortion=fixed_lens_distortion,
        min_solve_period_s=0.0,
        max_solve_duty=1.0,
    )


def run_session(
    seq: Sequence,
    focal_model: str = "varying",
    distortion: bool | None = None,
    stills: StillsConfig | None = None,
) -> tuple[list[MethodResult], Tracking]:
    """Frames one by one as the nodes run them: tracker -> CalibratorSession (the calibrator node's
    logic: IncrementalCalibrator, LM + keyframe MAP bundle adjustment), whose worker step runs inline
    after every frame with the node's default budget (so the timing holds all the work).

    focal_model "varying" (the node's default, a zooming camera) or "constant" (focal_model:=constant,
    a fixed lens). `distortion` is estimate_distortion:=true: for a varying focal length
    lens/hook.SessionLensHook in front of the session exactly as nodes/calibrator.py wires it
    (homographies corrected per frame, keyframe matches through the hook, its `work` after every session
    step, D from its plumb_bob fit); for a fixed lens one coefficient in the session's adjustment;
    None: as the product is configured for the input (estimate_distortion for a distorted lens).
    "As published" counts the frames the product published as CONVERGED (DESIGN.md 4: the statuses
    before it say the calibration is not yet to be taken). `stills`: the stills front end's
    configuration for the real sets (track_sequence)."""
    from ptz_selfcal.lens.hook import SessionLensHook
    from ptz_selfcal.online.session import CalibratorSession, FrameInput

    fixed = focal_model == "constant"
    distortion = seq.distorted if distortion is None else distortion
    config = session_config(focal_model, fixed and distortion)
    session = CalibratorSession(config)
    lens = SessionLensHook(config.nominal_focal) if distortion and not fixed else None
    if lens is not None:
        session.set_distortion(lens.distortion)
    published: dict[int, tuple[Array, Array, str]] = {}
    statuses: dict[str, int] = {}
    w, h = seq.size
    dt = STILL_INTERVAL_S if seq.fixed_focal else 1.0 / FPS
    calib_cpu = 0.0
    last_message: list[str] = []

    def on_frame(i: int, frame: np.ndarray, scale: float, result) -> None:
        nonlocal calib_cpu
        c0 = time.process_time()
        for link in result.links:  # the tracker node's KeyframeMatches
            if lens is not None:
                lens.matches(link.target_id, link.source_id, link.target_points, link.source_points)
            else:
                session.add_keyframe_matches(
                    link.target_id, link.source_id, link.target_points, link.source_points, link.H
                )
        state = result.state.value
        kid = -1 if result.keyframe_id is None else int(result.keyframe_id)
        ref = "" if result.reference_id is None else str(result.reference_id)
        H = result.H_ref
        if lens is not None and state in HOMOGRAPHY_STATES:
            H, state = lens.frame(H, state, kid, ref, w, h)
        out = session.process(FrameInput(i * dt, H, state, w, h, kid, ref))
        last_message[:] = [out.message]
        if out.source == "calibration" and out.R is not None:
            published[i] = (out.K, out.R, out.status)
        status = str(out.status)  # a plain name: the note prints this dict
        statuses[status] = statuses.get(status, 0) + 1
        session.step(SESSION_BUDGET_S)
        if lens is not None:
            lens.work(session)
        calib_cpu += time.process_time() - c0

    tracking = track_sequence(seq, on_frame, stills)
    ms = per_frame_ms(tracking, len(seq.frames))
    if fixed:
        name = (
            "ptz_selfcal fixed lens" + (" + radial dist." if distortion else "") + " (focal_model constant)"
        )
    else:
        name = ONLINE
    rows = [published_row(name, seq, published, ms)]
    rows[0].note += f" (published statuses {statuses})"
    if distortion:
        rows[0].note += "; estimate_distortion: true"
    if last_message:
        rows[0].note += f"; last frame's message: {last_message[-1][:110]}"
    if seq.fixed_focal:
        n = len(seq.frames)
        stages = ", ".join(f"{k} {1000.0 * v / n:.0f}" for k, v in tracking.stage_cpu.items())
        rows[0].note += (
            f"; CPU/frame: front end {1000.0 * (tracking.cpu_seconds - calib_cpu) / n:.0f} ms ({stages}), "
            f"calibration {1000.0 * calib_cpu / n:.0f} ms"
        )
    calibrator = session.calibration.calibrator
    if calibrator is not None and session.reference_id not in (None, ""):
        calibrator.reference_id = int(session.reference_id)  # the map the session calibrated last
    final = final_state_row(seq, tracking, calibrator, ms, lens)
    final.method = f"{name}, final state"
    if calibrator is not None and calibrator.last_solve is not None:
        solve = calibrator.last_solve
        final.note += (
            f"; state {calibrator.state.value}, 1-sigma f {100 * solve.sigma_f_ref / solve.K_ref[1, 1]:.2g}%"
        )
    if fixed and distortion and session.calibration.solver.shared_lam is not None:
        final.note += f"; lam {session.calibration.solver.shared_lam:.4f}"
    elif distortion:
        final.note += "; estimate_distortion: true"
    return [*rows, final], tracking


def per_frame_ms(tracking: Tracking, n_frames: int) -> tuple[float, float]:
    """(wall, CPU) milliseconds per frame of a tracking pass (with whatever ran inside it)."""
    return 1000.0 * tracking.seconds / n_frames, 1000.0 * tracking.cpu_seconds / n_frames


def published_row(name: str, seq: Sequence, published: dict, ms: tuple[float, float]) -> MethodResult:
    """The K published as CONVERGED for each evaluation frame after the warm-up (DESIGN.md section 7)."""
    warm = metrics.warmup_frames(len(seq.frames))
    idx = np.array(
        [
            i
            for i in seq.eval_idx
            if i in published and published[i][2] == CalibrationStatus.CONVERGED and i >= warm
        ],
        dtype=np.intp,
    )
    note = f"as published CONVERGED, frames >= {warm}" + ("" if len(idx) else ": none")
    others = [i for i in published if i >= warm and published[i][2] != CalibrationStatus.CONVERGED]
    if seq.f_reference is not None and others:  # what the statuses kept a user from taking
        err = [100.0 * abs(published[i][0][0, 0] / seq.f_reference - 1.0) for i in others]
        note += f"; frames published as not converged: f median {np.median(err):.1f}% off AutoStitch"
    if not len(idx):
        return failed(name, True, note)
    K = np.array([published[i][0] for i in idx])
    R = np.array([published[i][1] for i in idx])
    return MethodResult(name, True, idx, K, R, ms[0], note=note, cpu_ms_per_frame=ms[1])


def final_state_row(
    seq: Sequence, tracking: Tracking, calibrator, ms: tuple[float, float], lens=None
) -> MethodResult:
    """Every evaluation frame through the calibrator's final state (O(1) per frame, after the run).

    With a lens hook (estimate_distortion) each frame's tracked homography is first corrected with
    the hook's final distortion estimate, as the node does per frame. A fixed lens gives every frame
    its one K (IncrementalCalibrator.frame_intrinsics with the constant-focal model)."""
    name = f"{ONLINE}, final state"
    if calibrator is None or not calibrator.calibrated:
        return failed(name, True, "never calibrated")
    idx = np.array(
        [i for i in seq.eval_idx if tracking.H_ref[i] is not None
         and tracking.reference_id[i] == calibrator.reference_id], dtype=np.intp,
    )  # fmt: skip
    keep, KR = [], []
    for i in idx:
        H = tracking.H_ref[i]
        if lens is not None and lens.lens is not None:
            H = lens.lens.frame_homography(H, int(tracking.results[i].keyframe_id))
            if H is None:
                continue
        try:
            KR.append(calibrator.frame_intrinsics(H)[:2])
            keep.append(i)
        except (SelfCalibrationError, np.linalg.LinAlgError, ValueError):
            continue  # the calibrator refuses this frame's homography: no estimate
    if not keep:
        return failed(name, True, "no frame accepted")
    idx = np.array(keep, dtype=np.intp)
    K = np.array([k for k, _ in KR])
    R = np.array([r for _, r in KR])
    note = "end-of-run calibration replayed"
    return MethodResult(name, True, idx, K, R, ms[0], note=note, cpu_ms_per_frame=ms[1])


# --------------------------------------------------------------------------------------------------
# Errors and the table
# --------------------------------------------------------------------------------------------------
@dataclass
class Row:
    input: str
    method: str
    online: bool
    frames: str
    f_med: float = float("nan")  # percent
    f_p90: float = float("nan")
    pp_med: float = float("nan")  # pixels
    rot_med: float = float("nan")  # degrees
    ms: float = float("nan")
    cpu_ms: float = float("nan")
    f_vs_autostitch: float = float("nan")  # percent (median over frames)
    f_vs_opencv: float = float("nan")
    note: str = ""


def evaluate(seq: Sequence, res: MethodResult, f_opencv: float | None) -> Row:
    n_eval = len(seq.eval_idx)
    frames = f"{len(res.frame_idx)}/{n_eval}"
    row = Row(seq.name, res.method, res.online, frames, ms=res.ms_per_frame, cpu_ms=res.cpu_ms_per_frame)
    row.note = res.note
    if not len(res.frame_idx):
        return row
    order = np.argsort(res.frame_idx)
    idx, K, R = res.frame_idx[order], res.K[order], res.R[order]
    f = K[:, 0, 0]
    if seq.K_true is not None:
        K_true = seq.K_true[idx]
        e = 100.0 * metrics.focal_errors(f, K_true[:, 0, 0])
        row.f_med, row.f_p90 = float(np.median(e)), float(np.percentile(e, 90))
        row.pp_med = float(np.median(metrics.principal_point_errors(K[:, :2, 2], K_true[:, :2, 2])))
    if seq.R_true is not None and len(idx) > 1:
        pairs = np.array([(a, b) for a in range(len(idx)) for b in range(a + 1, len(idx))])
        rot = metrics.pairwise_rotation_errors(R, seq.R_true[idx], pairs)
        row.rot_med = float(np.degrees(np.median(rot)))
    if seq.f_reference is not None:
        row.f_vs_autostitch = float(np.median(100.0 * np.abs(f - seq.f_reference) / seq.f_reference))
    if f_opencv is not None and not res.method.startswith("OpenCV stitching"):
        row.f_vs_opencv = float(np.median(100.0 * np.abs(f - f_opencv) / f_opencv))
    return row


def _fmt(value: float, spec: str) -> str:
    return "-" if not np.isfinite(value) else format(value, spec)


HEADER = (
    f"{'input':<11} {'method':<66} {'online':<6} {'frames':>7} {'f med%':>8} {'f p90%':>8} {'pp px':>7} "
    f"{'rot deg':>8} {'wall ms':>8} {'cpu ms':>8} {'f-AS %':>7} {'f-OCV %':>7}  note"
)


def format_row(r: Row) -> str:
    return (
        f"{r.input:<11} {r.method[:66]:<66} {'yes' if r.online else 'no':<6} {r.frames:>7} "
        f"{_fmt(r.f_med, '.3f'):>8} {_fmt(r.f_p90, '.3f'):>8} {_fmt(r.pp_med, '.2f'):>7} "
        f"{_fmt(r.rot_med, '.4f'):>8} {_fmt(r.ms, '.1f'):>8} {_fmt(r.cpu_ms, '.1f'):>8} "
        f"{_fmt(r.f_vs_autostitch, '.2f'):>7} "
        f"{_fmt(r.f_vs_opencv, '.2f'):>7}  {r.note}"
    ).rstrip()


def _ratio(a: float, b: float) -> float:
    return a / b if np.isfinite(a) and np.isfinite(b) and b > 0 else float("nan")


def target_lines(rows: list[Row]) -> list[str]:
    """The issue's targets, checked on the measured rows: one line per online configuration that
    calibrated (as published, with its end-of-run state where the target is a focal length)."""
    out = []
    by_input: dict[str, dict[str, Row]] = {}
    for r in rows:
        by_input.setdefault(r.input, {})[r.method] = r
    for name, group in by_input.items():
        ocv = next((r for m, r in group.items() if m.startswith("OpenCV stitching")), None)
        online = [r for r in group.values() if r.online and r.note.startswith("as published")]
        for ours in online:
            final = group.get(f"{ours.method}, final state")
            if ocv is None:
                continue
            if int(ours.frames.split("/")[0]) == 0:
                if final is not None and np.isfinite(final.f_vs_autostitch):
                    out.append(
                        f"{name} [{ours.method}]: no frame published CONVERGED; focal vs AutoStitch "
                        f"{final.f_vs_autostitch:.2f}% final state (target <= 2%); {_speed_up(ocv, final)}"
                    )
                continue
            out.append(_target_line(name, ocv, ours, final))
    return out


def _speed_up(ocv: Row, ours: Row) -> str:
    """OpenCV's time per frame over ours, wall and CPU; when short of 100x, the budget it implies."""
    wall, cpu = _ratio(ocv.ms, ours.ms), _ratio(ocv.cpu_ms, ours.cpu_ms)
    line = f"speed-up {wall:.0f}x wall, {cpu:.0f}x CPU (target >= 100x"
    if not wall >= 100.0:
        line += f": not met, needs <= {ocv.ms / 100.0:.2f} ms wall per frame, ours {ours.ms:.1f}"
    return line + ")"


def _target_line(name: str, ocv: Row, ours: Row, final: Row | None) -> str:
    line = f"{name} [{ours.method}]: {_speed_up(ocv, ours)}"
    if name.startswith("clean") or name.startswith("longfocal"):
        gap = ours.f_p90 - ocv.f_p90
        line += f"; focal p90 ours - OpenCV = {gap:+.3f} points (target <= +0.1)"
    elif name.startswith("distorted"):
        ratio = ours.f_p90 / ocv.f_p90 if ocv.f_p90 > 0 else float("nan")
        line += f"; focal p90 ours / OpenCV = {ratio:.3f} (target <= 0.5)"
        if final is not None:
            line += f"; final state p90 {final.f_p90:.3f}% vs OpenCV {ocv.f_p90:.3f}%"
    if np.isfinite(ours.f_vs_autostitch):
        line += f"; focal vs AutoStitch {ours.f_vs_autostitch:.2f}% as published"
        if final is not None:
            line += f", {final.f_vs_autostitch:.2f}% final state"
        line += " (target <= 2%)"
    return line


# --------------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------------
def load_input(name: str, quick: bool, workdir: Path) -> Sequence:
    if name in REAL:
        return load_real_set(name)
    n_frames = 40 if quick else 150
    return synth_sequence(name, SYNTH[name], n_frames, workdir)


def synth_sequence(name: str, spec: SynthSpec, n_frames: int, workdir: Path) -> Sequence:
    """A `ptz-selfcal synth` bag read back (in-process rendering when the command is not there)."""
    try:
        from ptz_selfcal.tools import synth  # noqa: F401
    except ImportError:
        return render_sequence(name, spec, n_frames)
    return synth_bag_sequence(name, spec, n_frames, workdir)


def synth_bag_sequence(name: str, spec: SynthSpec, n_frames: int, workdir: Path) -> Sequence:
    """Render with `ptz-selfcal synth` into workdir and read images and ground truth back."""
    bag = workdir / name
    pano = str(DATA / "panoramas" / spec.panorama)
    options = {
        "frames": n_frames, "width": spec.width, "height": spec.height, "fps": FPS, "hfov": spec.hfov_deg,
        "zoom-max": spec.zoom_max, "pan-amplitude": spec.pan_deg, "tilt-amplitude": spec.tilt_deg,
        "distortion": spec.distortion, "jobs": 2,
    }  # fmt: skip
    cmd = [sys.executable, "-m", "ptz_selfcal.tools.cli", "synth", pano, str(bag), "--quiet"]
    cmd += [item for key, value in options.items() for item in (f"--{key}", str(value))]
    subprocess.run(cmd, check=True)
    frames, K, R = read_synth_bag(bag)
    args = " ".join(cmd[4:]).replace(str(DATA / "panoramas") + "/", "").replace(str(workdir) + "/", "")
    source = f"ptz-selfcal synth {args}"
    return Sequence(
        name, frames, np.arange(0, len(frames), STRIDE), K, R, source=source, distorted=spec.distortion > 0
    )


def read_synth_bag(bag: Path) -> tuple[list[np.ndarray], Array, Array]:
    """(mono8 frames, true K (n, 3, 3), true world-to-camera R (n, 3, 3)) in image order."""
    from ptz_selfcal import topics
    from ptz_selfcal.camera.geometry import ptz_rotation
    from ptz_selfcal.tools.bagio import BagReader, deserialize

    images: dict[int, np.ndarray] = {}
    K: dict[int, Array] = {}
    R: dict[int, Array] = {}
    with BagReader(bag) as reader:
        for m in reader.messages():
            msg = deserialize(m.raw, m.msgtype)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            if m.topic == topics.bag_topic(topics.IMAGE_COMPRESSED):
                images[stamp] = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE)
            elif m.topic == topics.bag_topic(topics.IMAGE_RAW):
                images[stamp] = _gray(_raw_image(msg))
            elif m.topic == topics.bag_topic(topics.GT_CAMERA_INFO):
                K[stamp] = np.asarray(msg.k, dtype=float).reshape(3, 3)
            elif m.topic == topics.bag_topic(topics.GT_JOINT_STATES):
                joints = dict(zip(msg.name, msg.position))
                R[stamp] = ptz_rotation(joints["pan"], joints["tilt"])
    stamps = sorted(images)
    return [images[t] for t in stamps], np.array([K[t] for t in stamps]), np.array([R[t] for t in stamps])


def _raw_image(msg) -> np.ndarray:
    data = np.asarray(msg.data, np.uint8)
    channels = 1 if msg.encoding == "mono8" else 3
    image = data.reshape(msg.height, msg.step)[:, : msg.width * channels].reshape(msg.height, msg.width, -1)
    if msg.encoding == "rgb8":
        image = image[..., ::-1]
    return np.ascontiguousarray(image.squeeze())


def run_input(
    seq: Sequence, features: str, log: Callable[[str], None], cache: Path | None = None
) -> list[Row]:
    online, tracking = run_session(seq)
    if seq.fixed_focal:  # a fixed lens: the calibrator node with focal_model:=constant
        for distortion in (False, True):
            online += run_session(seq, "constant", distortion)[0]
    log(f"  [{seq.name}] tracked {len(seq.frames)} frames in {tracking.seconds:.1f} s")
    ocv = run_opencv(seq, features, cache)
    log(f"  [{seq.name}] OpenCV: {ocv.ms_per_frame:.0f} ms/frame {ocv.note}")
    results = [ocv, *paper_rows(seq, tracking), *online]
    f_ocv = float(np.median(ocv.K[:, 0, 0])) if len(ocv.frame_idx) and seq.K_true is None else None
    return [evaluate(seq, r, f_ocv) for r in results]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short sequences (40 frames instead of 150)")
    parser.add_argument("--inputs", default=",".join([*SYNTH, *REAL]), help="comma-separated input names")
    parser.add_argument("--features", default="sift", choices=("sift", "orb"), help="OpenCV feature finder")
    parser.add_argument("--out", type=Path, default=None, help=f"write the table here (full run: {RESULTS})")
    parser.add_argument(
        "--opencv-cache",
        type=Path,
        default=None,
        help="reuse OpenCV results stored here by an earlier run on byte-identical frames (else store them)",
    )
    parser.add_argument(
        "--merge", type=Path, nargs="+", help="merge reports of runs made in parallel into one"
    )
    args = parser.parse_args(argv)
    if args.merge:
        return write_text(merge_reports([p.read_text() for p in args.merge]), args.out)
    names = [n.strip() for n in args.inputs.split(",") if n.strip()]
    unknown = [n for n in names if n not in SYNTH and n not in REAL]
    if unknown:
        parser.error(f"unknown inputs {unknown}; choose from {[*SYNTH, *REAL]}")

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    rows: list[Row] = []
    sources = []
    with tempfile.TemporaryDirectory(prefix="peers_") as tmp:
        for name in names:
            seq = load_input(name, args.quick, Path(tmp))
            sources.append(f"{name}: {seq.source}, {len(seq.frames)} frames {seq.size[0]}x{seq.size[1]}")
            rows += run_input(seq, args.features, log, args.opencv_cache)
    return write_text(report(rows, sources, args), args.out)


def write_text(text: str, out: Path | None) -> int:
    print(text)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")
    return 0


def _sections(text: str) -> list[list[str]]:
    """A report's blank-line separated blocks: command+sources, table, targets, note."""
    blocks: list[list[str]] = [[]]
    for line in text.rstrip("\n").splitlines():
        if line:
            blocks[-1].append(line)
        else:
            blocks.append([])
    return blocks


def merge_reports(texts: list[str]) -> str:
    """One table from the reports of several runs (each run's command is kept)."""
    parts = [_sections(t) for t in texts]

    def run_line(line: str) -> bool:  # a run's command and its date / code / load line
        return line.startswith("$ ") or line[:2].isdigit()

    commands = [line for p in parts for line in p[0] if run_line(line)]
    explanation = next(line for line in parts[0][0] if line.startswith("Errors on"))
    sources = [line for p in parts for line in p[0] if not run_line(line) and line != explanation]
    rows = [line for p in parts for line in p[1][1:]]
    targets = [line for p in parts for line in p[2]]
    return "\n".join(
        [*commands, explanation, *sources, "", HEADER, *rows, "", *targets, "", opencv_peer.PORT_NOTE]
    )


def code_revision() -> str:
    """The commit the run used, and whether src/ had uncommitted changes (a shared working tree)."""
    root = Path(__file__).resolve().parents[1]

    def git(*args: str) -> str:
        out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=False)
        return out.stdout

    head = git("rev-parse", "--short", "HEAD").strip() or "unknown"
    dirty = [Path(ln[3:]).name for ln in git("status", "--porcelain", "--", "src").splitlines() if ln.strip()]
    return f"code: {head}" + (f" + uncommitted changes in {', '.join(dirty)}" if dirty else "")


def report(rows: list[Row], sources: list[str], args: argparse.Namespace) -> str:
    cmd = "ros2_ws/venv/bin/python benchmarks/peers.py " + " ".join(sys.argv[1:])
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lines = [
        f"$ {cmd.strip()}",
        f"{stamp}, {code_revision()}; load average at the end {load} (2 CPUs shared: wall times inflated)",
        "Errors on every 5th frame (real sets: every frame); f = fx; rotation = median pairwise |angle| "
        "difference (DESIGN.md 7); ms/frame = wall time / frames the method consumed (OpenCV: every 5th "
        "frame; ptz_selfcal: every frame; batch rows: tracking per frame + solve per evaluated frame).",
        *sources,
        "",
        HEADER,
        *[format_row(r) for r in rows],
        "",
        *target_lines(rows),
        "",
        opencv_peer.PORT_NOTE,
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
