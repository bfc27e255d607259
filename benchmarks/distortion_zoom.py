"""Benchmark (issue 6): radial distortion estimated from rendered images while zooming, its effect on
self-calibration, and the learned zoom model.

Keyframes are rendered from an equirectangular panorama (1280x720, zoom 1x -> 3x, division-model lens with
the corner moving by 12% of the half-diagonal at the wide end, shrinking as 1/f, principal point = distortion
centre offset from the image centre). Matches between keyframes: SIFT + MAGSAC for a first homography, then
KLT on the second image warped into the first by it (as the tracker does), then a loose MAGSAC. No ground
truth enters the estimation; nominal focal lengths are 10% off.

Prints: per-keyframe distortion error (DESIGN.md section 7, plumb_bob output against the division truth);
the same for in-between frames matched to a keyframe (their own lam, with and without the curve as prior,
or the curve alone); focal error of LM self-calibration (eq. 22, constant pp) over the keyframes from
homographies on corrected coordinates, from distorted-point homographies corrected afterwards (grid), and
uncorrected; the zoom model (fed with the corrected keyframe calibrations) predicting f from the zoom
encoder alone, and after a save/load restart.

Run: ros2_ws/venv/bin/python benchmarks/distortion_zoom.py [--panorama P] [--sequences 3] [--keyframes 9]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ptz_selfcal.camera.distortion import (
    division_lambda_for_corner_shift,
    division_to_plumb_bob,
    division_undistort,
    max_distortion_difference,
)
from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation
from ptz_selfcal.frontend.homography import estimate_homography
from ptz_selfcal.lens.curve import DistortionVsFocal
from ptz_selfcal.lens.estimation import (
    KeyframeMatch,
    estimate_frame_distortion,
    estimate_keyframe_distortion,
    undistorted_homography,
)
from ptz_selfcal.selfcal.lm import lm_selfcalibration
from ptz_selfcal.zoom.model import ZoomModel

W, H = 1280, 720
F_WIDE = 1108.5  # 60 degrees horizontal field of view
ZOOM_MAX = 3.0
PP = np.array([(W - 1) / 2 + 6.0, (H - 1) / 2 - 4.0])
COUNTS = 16384.0


def lam_true(f: float) -> float:
    return division_lambda_for_corner_shift(0.12 * F_WIDE / f, W, H, f)


def zoom_counts(f):
    """A zoom encoder: counts not proportional to f (log-like with a bend), monotone."""
    t = np.log(np.asarray(f) / F_WIDE) / np.log(ZOOM_MAX)
    return COUNTS * (0.7 * t + 0.3 * t**2)


def render(pano_levels, K, R, lam):
    gx, gy = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    und = division_undistort(np.column_stack([gx.ravel(), gy.ravel()]), lam, K[:2, 2], K[0, 0])
    rays = (R.T @ np.linalg.inv(K) @ np.column_stack([und, np.ones(len(und))]).T).T
    lon = np.arctan2(rays[:, 0], rays[:, 2])
    lat = np.arctan2(-rays[:, 1], np.hypot(rays[:, 0], rays[:, 2]))
    level = int(
        np.clip(np.round(np.log2(pano_levels[0].shape[1] / (2 * np.pi * K[0, 0]))), 0, len(pano_levels) - 1)
    )
    img = pano_levels[level]
    pw, ph = img.shape[1], img.shape[0]
    x = (lon / (2 * np.pi) + 0.5) * pw - 0.5
    y = (0.5 - lat / np.pi) * ph - 0.5
    out = cv2.remap(
        img,
        np.mod(x, pw).reshape(H, W).astype(np.float32),
        y.reshape(H, W).astype(np.float32),
        cv2.INTER_LINEAR,
    )
    return out


def match_pair(img_i, img_j, sift):
    """Distorted pixel matches i -> j: SIFT + MAGSAC, then KLT on image j warped into image i."""
    ki, di = sift.detectAndCompute(img_i, None)
    kj, dj = sift.detectAndCompute(img_j, None)
    if di is None or dj is None:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(di, dj, k=2)
    good = [m for m, n in (p for p in knn if len(p) == 2) if m.distance < 0.75 * n.distance]
    if len(good) < 20:
        return None
    pi = np.float64([ki[m.queryIdx].pt for m in good])
    pj = np.float64([kj[m.trainIdx].pt for m in good])
    Hij, mask = cv2.findHomography(pi, pj, cv2.USAC_MAGSAC, 6.0)
    if Hij is None:
        return None
    warped = cv2.warpPerspective(
        img_j, np.linalg.inv(Hij), (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_FILL_OUTLIERS
    )
    valid = cv2.warpPerspective(np.full((H, W), 255, np.uint8), np.linalg.inv(Hij), (W, H)) == 255
    valid = cv2.erode(valid.astype(np.uint8), np.ones((31, 31), np.uint8)) > 0
    corners = cv2.goodFeaturesToTrack(img_i, 800, 0.01, 20, mask=valid.astype(np.uint8) * 255, blockSize=7)
    if corners is None or len(corners) < 30:
        return None
    c = corners.astype(np.float32)
    tracked, status, _ = cv2.calcOpticalFlowPyrLK(img_i, warped, c, None, winSize=(21, 21), maxLevel=3)
    back, status_b, _ = cv2.calcOpticalFlowPyrLK(warped, img_i, tracked, None, winSize=(21, 21), maxLevel=3)
    ok = (status.ravel() == 1) & (status_b.ravel() == 1) & (np.linalg.norm(back - c, axis=2).ravel() < 0.3)
    src = c.reshape(-1, 2)[ok].astype(float)
    dst_w = tracked.reshape(-1, 2)[ok].astype(float)
    proj = np.column_stack([dst_w, np.ones(len(dst_w))]) @ Hij.T
    dst = proj[:, :2] / proj[:, 2:3]
    inside = np.all((dst >= 0) & (dst <= [W - 1, H - 1]), axis=1)
    src, dst = src[inside], dst[inside]
    # loose outlier rejection (distortion bends the homography by tens of pixels at the wide end)
    _, mask = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, 10.0)
    keep = mask.ravel().astype(bool)
    return src[keep], dst[keep]


def keyframe_path(n_kf: int, seed: int):
    rng = np.random.default_rng(seed)
    f = F_WIDE * ZOOM_MAX ** (np.arange(n_kf) / (n_kf - 1))
    pan, tilt = np.zeros(n_kf), np.zeros(n_kf)
    for k in range(1, n_kf):
        hfov = 2 * np.arctan(W / 2 / f[k])
        pan[k] = pan[k - 1] + 0.25 * hfov * rng.choice([-1.0, 1.0])
        tilt[k] = np.clip(tilt[k - 1] + 0.12 * hfov * rng.normal(), -0.3, 0.3)
    return f, pan, tilt


def run_sequence(pano_levels, n_kf, seed, noise_gray, rng):
    f, pan, tilt = keyframe_path(n_kf, seed)
    Ks = [intrinsic_matrix(fk, *PP) for fk in f]
    Rs = [ptz_rotation(p, t) for p, t in zip(pan, tilt)]
    imgs = []
    for K, R, fk in zip(Ks, Rs, f):
        img = render(pano_levels, K, R, lam_true(fk)).astype(np.float32)
        img = np.clip(img + rng.normal(0, noise_gray, img.shape), 0, 255).astype(np.uint8)
        imgs.append(img)
    sift = cv2.SIFT_create(nfeatures=3000)
    matches = []
    for i in range(n_kf):
        for j in (i + 1, i + 2):
            if j < n_kf:
                m = match_pair(imgs[i], imgs[j], sift)
                if m is not None and len(m[0]) >= 40:
                    matches.append(KeyframeMatch(i, j, m[0], m[1]))
    # in-between frames (zoom and pan interpolated geometrically / linearly), matched to keyframe k
    frames = []
    for k in range(n_kf - 1):
        for t in (0.25, 0.5, 0.75):
            fr = f[k] * (f[k + 1] / f[k]) ** t
            R = ptz_rotation(pan[k] + t * (pan[k + 1] - pan[k]), tilt[k] + t * (tilt[k + 1] - tilt[k]))
            img = render(pano_levels, intrinsic_matrix(fr, *PP), R, lam_true(fr)).astype(np.float32)
            img = np.clip(img + rng.normal(0, noise_gray, img.shape), 0, 255).astype(np.uint8)
            m = match_pair(imgs[k], img, sift)
            if m is not None and len(m[0]) >= 40:
                frames.append((k, fr, m[0], m[1]))
    return f, Ks, Rs, matches, frames


def summary(e) -> str:
    return f"median {np.median(e):.3f}  90th {np.percentile(e, 90):.3f}  max {np.max(e):.3f}"


def chain(Hs_consecutive):
    out = [np.eye(3)]
    for Hc in Hs_consecutive:
        out.append(Hc @ out[-1])
    return np.array([h / h[2, 2] for h in out])


def selfcal_focal_errors(H0j, f_true):
    res = lm_selfcalibration(H0j, (W, H), nominal_focal=F_WIDE)
    est = res.K[:, 0, 0]
    return np.abs(est / f_true - 1.0), res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--panorama", default="/work/shared/data/panoramas/building.jpg")
    ap.add_argument("--keyframes", type=int, default=9)
    ap.add_argument("--sequences", type=int, default=3)
    ap.add_argument("--noise", type=float, default=2.0, help="image noise, grey levels")
    args = ap.parse_args()
    t0 = time.time()
    pano = cv2.imread(args.panorama, cv2.IMREAD_GRAYSCALE)
    if pano is None:
        raise SystemExit(f"cannot read {args.panorama}")
    levels = [pano]
    for _ in range(5):
        levels.append(cv2.pyrDown(levels[-1]))
    rng = np.random.default_rng(0)
    zoom_model = ZoomModel()
    dist_err_kf, dist_err_curve, dist_err_centre, dist_err_div = [], [], [], []
    f_err_on, f_err_off, f_err_on_curve, f_err_grid = [], [], [], []
    all_f = []
    frame_errors: dict[str, list[float]] = {"free": [], "prior": [], "curve": []}
    print(
        f"panorama {Path(args.panorama).name}, {W}x{H}, zoom 1x-{ZOOM_MAX:g}x, "
        "corner shift 12% at the wide end"
    )
    for s in range(args.sequences):
        f, Ks, _, matches, frames = run_sequence(
            levels, args.keyframes, seed=10 + s, noise_gray=args.noise, rng=rng
        )
        n_pts = [len(m.pts_i) for m in matches]
        f_nominal = f * 1.10  # distortion estimation does not need the focal lengths (only lam / f^2 is seen)
        t_solve = time.process_time()
        est = estimate_keyframe_distortion(matches, f_nominal, PP)
        t_solve = time.process_time() - t_solve
        tied = estimate_keyframe_distortion(
            matches, f_nominal, PP, lam0=est.lam, curve=DistortionVsFocal(W, H)
        )
        centre = estimate_keyframe_distortion(matches, f_nominal, ((W - 1) / 2, (H - 1) / 2))
        for k in range(len(f)):
            truth = ("division", (lam_true(f[k]),), Ks[k])
            K_nom = intrinsic_matrix(f_nominal[k], *PP)
            k1, k2 = division_to_plumb_bob(est.lam[k], K_nom, W, H)
            dist_err_kf.append(max_distortion_difference(("plumb_bob", (k1, k2), K_nom), truth, W, H))
            dist_err_div.append(max_distortion_difference(("division", (est.lam[k],), K_nom), truth, W, H))
            k1, k2 = division_to_plumb_bob(tied.lam[k], K_nom, W, H)
            dist_err_curve.append(max_distortion_difference(("plumb_bob", (k1, k2), K_nom), truth, W, H))
            K_c = intrinsic_matrix(f_nominal[k], (W - 1) / 2, (H - 1) / 2)
            k1, k2 = division_to_plumb_bob(centre.lam[k], K_c, W, H)
            dist_err_centre.append(max_distortion_difference(("plumb_bob", (k1, k2), K_c), truth, W, H))
        # in-between frames: their own lam with the keyframe's fixed, free or with the curve as prior
        curve_fit = DistortionVsFocal(W, H).fit(f_nominal, est.lam, 1.0 / est.sigma_lam**2)
        for k, fr, p_kf, p_fr in frames:
            f_fr_nominal = fr * 1.10
            truth = ("division", (lam_true(fr),), intrinsic_matrix(fr, *PP))
            K_nom = intrinsic_matrix(f_fr_nominal, *PP)
            free = estimate_frame_distortion(p_kf, p_fr, est.lam[k], PP, f_nominal[k], f_fr_nominal)
            prior_lam = float(curve_fit.predict(f_fr_nominal))
            held = estimate_frame_distortion(
                p_kf, p_fr, est.lam[k], PP, f_nominal[k], f_fr_nominal, prior_lam, 0.01 * abs(prior_lam)
            )
            for name, lam in (("free", free.lam_j), ("prior", held.lam_j), ("curve", prior_lam)):
                k1, k2 = division_to_plumb_bob(lam, K_nom, W, H)
                frame_errors[name].append(
                    max_distortion_difference(("plumb_bob", (k1, k2), K_nom), truth, W, H)
                )
        # self-calibration on consecutive-keyframe homographies, chained to keyframe 0
        consecutive = [i for i, m in enumerate(matches) if m.j == m.i + 1]
        if len(consecutive) == len(f) - 1:
            H_on = chain([est.homographies[i] for i in consecutive])
            H_tied = chain([tied.homographies[i] for i in consecutive])
            H_off = chain([estimate_homography(matches[i].pts_i, matches[i].pts_j) for i in consecutive])
            e_on, res_on = selfcal_focal_errors(H_on, f)
            e_tied, _ = selfcal_focal_errors(H_tied, f)
            e_off, res_off = selfcal_focal_errors(H_off, f)
            # only the distorted-point homography at hand (no inliers): grid correction with the estimates
            H_grid = chain(
                [
                    undistorted_homography(
                        estimate_homography(matches[i].pts_i, matches[i].pts_j),
                        est.lam[matches[i].i],
                        est.lam[matches[i].j],
                        PP,
                        PP,
                        f_nominal[matches[i].i],
                        f_nominal[matches[i].j],
                        W,
                        H,
                    )
                    for i in consecutive
                ]
            )
            f_err_grid += list(selfcal_focal_errors(H_grid, f)[0])
            print(
                f"  sequence {s}: LM eq. 22 ok flag corrected {res_on.ok}, uncorrected {res_off.ok} "
                f"({res_off.message})"
            )
            f_err_on += list(e_on)
            f_err_on_curve += list(e_tied)
            f_err_off += list(e_off)
            # the calibrator's output for the zoom model: its own f, pp and the distortion at its own f
            for k in range(len(f)):
                K_est = res_on.K[k]
                lam_k = est.lam[k] * (K_est[0, 0] / f_nominal[k]) ** 2  # rescale_lambda to the estimated f
                k1, k2 = division_to_plumb_bob(lam_k, K_est, W, H)
                zoom_model.add_sample(float(zoom_counts(f[k])), K_est[0, 0], K_est[0, 2], K_est[1, 2], k1, k2)
                all_f.append(f[k])
        else:
            print(f"  sequence {s}: a consecutive keyframe pair failed to match; self-calibration skipped")
        print(
            f"  sequence {s}: {len(matches)} keyframe pairs, "
            f"matches per pair median {int(np.median(n_pts))}, "
            f"transfer rms {est.rms:.3f} px corrected / {est.rms_undistorted_model:.3f} px uncorrected, "
            f"distortion solve {t_solve:.2f} s CPU"
        )
    d0, d1, d2, d3 = (np.array(x) for x in (dist_err_div, dist_err_kf, dist_err_curve, dist_err_centre))
    print(
        f"distortion error of the division estimate itself (px): median {np.median(d0):.3f}  "
        f"max {d0.max():.3f}"
    )
    print("distortion error (DESIGN section 7, plumb_bob output vs division truth), pixels, all keyframes:")
    print("  per-keyframe lam       " + summary(d1))
    print("  lam tied by curve      " + summary(d2))
    print("  centre = image centre (pp error 7.2 px) " + summary(d3))
    for name, label in (
        ("free", "own lam, keyframe lam fixed"),
        ("prior", "own lam with the curve as prior (1%)"),
        ("curve", "lam from the curve alone"),
    ):
        e = np.array(frame_errors[name])
        print(
            f"in-between frames ({len(e)}), distortion error, {label}: median {np.median(e):.3f}  "
            f"90th {np.percentile(e, 90):.3f}  max {e.max():.3f} px"
        )
    if f_err_on:
        for name, e in (
            ("with distortion estimation (per-keyframe)", f_err_on),
            ("with distortion estimation (curve-tied)", f_err_on_curve),
            ("with grid-corrected distorted-point homographies", f_err_grid),
            ("without distortion estimation", f_err_off),
        ):
            e = 100 * np.array(e)
            print(
                f"LM self-calibration focal error {name}: median {np.median(e):.3f}%  "
                f"90th {np.percentile(e, 90):.3f}%  max {e.max():.3f}%"
            )
    if zoom_model.ready():
        lo, hi = zoom_model.covered_range()
        f_lo, f_hi = min(all_f), max(all_f)
        grid_f = np.geomspace(f_lo, f_hi, 200)
        grid_z = zoom_counts(grid_f)
        pred = np.array([zoom_model.predict(z).K[0, 0] for z in grid_z])
        err = 100 * np.abs(pred / grid_f - 1)
        print(
            f"zoom model ({zoom_model.sample_count} keyframe samples, zoom {lo:.0f}-{hi:.0f} counts): "
            "focal from "
            f"the encoder alone over the visited range: median {np.median(err):.3f}%  max {err.max():.3f}%"
        )
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "zoom_model.yaml"
            zoom_model.save(path)
            restarted = ZoomModel.load(path)
        first_zoom = float(zoom_counts(F_WIDE * 1.4))
        p = restarted.predict(first_zoom)
        print(
            f"restarted calibrator, first frame at {F_WIDE * 1.4:.1f} px: predicted f {p.K[0, 0]:.1f} px "
            f"(error {100 * abs(p.K[0, 0] / (F_WIDE * 1.4) - 1):.3f}%, sigma_f {p.sigma_f:.1f} px, "
            f"in_range {p.in_range})"
        )
        truth = ("division", (lam_true(F_WIDE * 1.4),), intrinsic_matrix(F_WIDE * 1.4, *PP))
        print(
            f"  its distortion error {max_distortion_difference(('plumb_bob', p.D, p.K), truth, W, H):.3f} px"
        )
    print(f"elapsed {time.time() - t0:.1f} s")


if __name__ == "__main__":
    main()
