"""`ptz-selfcal synth`: topics, counts, stamps, exact ground truth, determinism and bad input."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ptz_selfcal import topics
from ptz_selfcal.camera.distortion import division_corner_shift, division_distort, division_undistort
from ptz_selfcal.camera.geometry import apply_homography, infinite_homography, ptz_rotation, relative_rotation
from ptz_selfcal.sim.render import CameraProfile, ZoomEncoder, focal_from_hfov
from ptz_selfcal.tools import cli
from ptz_selfcal.tools.bagio import BagReader, deserialize

PANORAMA = Path(__file__).resolve().parents[2] / "bags" / "source" / "examplepano.jpg"
W, H, FRAMES, FPS = 320, 180, 20, 30.0
START_NS = 1_767_225_600 * 10**9
DEFAULT_HFOV = 54.0  # synth's documented default, deliberately not the calibrator's prior
# A short, gentle sequence (a few degrees and a few % zoom per frame) so that consecutive frames overlap.
MOTION = ["--pan-amplitude", "10", "--tilt-amplitude", "3", "--zoom-max", "1.5"]
CLI = "import sys; from ptz_selfcal.tools.cli import main; sys.exit(main())"  # as the entry point does
SHORT = [
    str(PANORAMA),
    "",
    "--frames",
    str(FRAMES),
    "--width",
    str(W),
    "--height",
    str(H),
    *MOTION,
    "--quiet",
]


def synth(monkeypatch: pytest.MonkeyPatch, out: Path, *extra: str) -> int:
    """Run `ptz-selfcal synth` in-process (the CLI imports a command's options from sys.argv)."""
    argv = ["synth", *[str(out) if a == "" else a for a in SHORT], *extra]
    monkeypatch.setattr(sys, "argv", ["ptz-selfcal", *argv])
    return cli.main(argv)


def read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    out: dict[str, list[tuple[int, object]]] = {}
    with BagReader(path) as reader:
        for m in reader.messages():
            out.setdefault(m.topic, []).append((m.timestamp_ns, deserialize(m.raw, m.msgtype)))
    return out


def stamp_ns(msg: object) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec  # type: ignore[attr-defined]


def profile(corner_shift: float = 0.0) -> CameraProfile:
    """The profile the defaults + MOTION describe, built independently of tools/synth.py."""
    return CameraProfile(
        width=W, height=H, period=(FRAMES - 1) / FPS, f_wide=focal_from_hfov(W, DEFAULT_HFOV), zoom_max=1.5,
        pan_amplitude=np.radians(10.0), tilt_amplitude=np.radians(3.0), corner_shift=corner_shift,
    )  # fmt: skip


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("synth")
    (root / "again").mkdir()
    paths = {"jpeg": root / "jpeg", "again": root / "again" / "jpeg", "mono8": root / "mono8"}
    with pytest.MonkeyPatch.context() as mp:
        assert synth(mp, paths["jpeg"]) == 0
        assert synth(mp, paths["again"], "--jobs", "1") == 0
        assert synth(mp, paths["mono8"], "--format", "mono8", "--distortion", "0.12", "--seed", "5") == 0
    return paths


def test_topics_counts_and_stamps(bags: dict[str, Path]) -> None:
    msgs = read_bag(bags["jpeg"])
    assert set(msgs) == {
        "/ptz/image_raw/compressed",
        "/ptz/joint_states",
        "/ptz/ground_truth/camera_info",
        "/ptz/ground_truth/joint_states",
    }
    images = msgs["/ptz/image_raw/compressed"]
    expected = [START_NS + round(i * 1e9 / FPS) for i in range(FRAMES)]
    assert [stamp_ns(m) for _, m in images] == expected
    assert [t for t, _ in images] == expected  # bag time = header stamp
    for topic in ("/ptz/ground_truth/camera_info", "/ptz/ground_truth/joint_states"):
        assert [stamp_ns(m) for _, m in msgs[topic]] == expected  # one per image, same stamp
    assert all(m.format == "jpeg" and m.header.frame_id == topics.CAMERA_FRAME_ID for _, m in images)
    first = cv2.imdecode(images[0][1].data, cv2.IMREAD_UNCHANGED)
    assert first.shape == (H, W, 3)
    # encoders: 15 Hz, bracketing every image stamp + 40 ms lag
    enc = [stamp_ns(m) for _, m in msgs["/ptz/joint_states"]]
    assert np.allclose(np.diff(enc), 1e9 / 15.0, atol=1.0)
    assert enc[0] < expected[0] and enc[-1] > expected[-1] + 40_000_000
    assert all(list(m.name) == ["pan", "tilt", "zoom"] for _, m in msgs["/ptz/joint_states"])
    times = [t for topic in msgs.values() for t, _ in topic]
    assert len(times) == FRAMES * 3 + len(enc)


def test_defaults_are_not_the_calibrators_prior(bags: dict[str, Path]) -> None:
    """A first bag made with the defaults must be solved for: neither its focal length nor its principal
    point is what the shipped parameter file assumes before the first calibration."""
    config = Path(__file__).resolve().parents[2] / "src" / "ptz_selfcal" / "config" / "ptz_selfcal.yaml"
    prior = yaml.safe_load(config.read_text())["/**/calibrator"]["ros__parameters"]
    assert prior["nominal_focal_px"] == 0.0  # the prior comes from nominal_hfov_deg
    info = read_bag(bags["jpeg"])["/ptz/ground_truth/camera_info"][0][1]
    f_prior = focal_from_hfov(W, prior["nominal_hfov_deg"])
    assert abs(info.k[0] / f_prior - 1.0) > 0.05, (info.k[0], f_prior)
    assert np.hypot(info.k[2] - (W - 1) / 2, info.k[5] - (H - 1) / 2) > 10.0


def test_ground_truth_matches_profile(bags: dict[str, Path]) -> None:
    msgs = read_bag(bags["jpeg"])
    truth = profile().state(np.arange(FRAMES) / FPS)
    zoom = ZoomEncoder(truth.f[0])
    for i, (_, info) in enumerate(msgs["/ptz/ground_truth/camera_info"]):
        K = np.asarray(info.k).reshape(3, 3)
        np.testing.assert_allclose(K, truth.K(i), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(info.p).reshape(3, 4)[:, :3], K)
        assert (info.width, info.height) == (W, H)
        assert info.distortion_model == "plumb_bob" and not np.any(info.d)
    K0 = np.asarray(msgs["/ptz/ground_truth/camera_info"][0][1].k).reshape(3, 3)
    np.testing.assert_allclose(K0[:2, 2], [159.5 + 15.0, 89.5 - 10.0])  # default pp offset (15, -10)
    for i, (_, js) in enumerate(msgs["/ptz/ground_truth/joint_states"]):
        np.testing.assert_allclose(
            js.position, [truth.pan[i], truth.tilt[i], zoom.counts(truth.f[i])], rtol=1e-12
        )
    # encoders: stamped t = state at t - 40 ms, noise 0.01 deg and ~2 counts
    enc = msgs["/ptz/joint_states"]
    t = (np.array([stamp_ns(m) for _, m in enc]) - START_NS) * 1e-9
    pan_true, _ = profile().pan_tilt(t - 0.040)
    pan = np.array([m.position[0] for _, m in enc])
    assert np.degrees(np.max(np.abs(pan - pan_true))) < 0.05
    counts = np.array([m.position[2] for _, m in enc])
    assert np.all(counts == np.round(counts))
    assert np.max(np.abs(counts - zoom.counts(profile().focal(t - 0.040)))) < 10.0


def _gray(msg: object) -> np.ndarray:
    if hasattr(msg, "format"):
        return cv2.imdecode(np.asarray(msg.data), cv2.IMREAD_GRAYSCALE)
    return np.asarray(msg.data).reshape(msg.height, msg.step)[:, : msg.width]  # type: ignore[attr-defined]


def _warp_residuals(img_i, img_j, info_i, info_j, js_i, js_j, f_scale: float = 1.0) -> np.ndarray:
    """Image i warped into frame j by the ground truth (lens + H_ij = K_j R_j R_i^T K_i^-1); ECC then
    aligns image j to it with an affine warp: returns that warp's displacement (px) over the overlap,
    ~0 when the ground truth is exact."""
    K_i, K_j = (np.asarray(m.k).reshape(3, 3) for m in (info_i, info_j))
    lam_i, lam_j = (float(m.d[0]) if m.distortion_model == "division" else 0.0 for m in (info_i, info_j))
    R_i, R_j = (ptz_rotation(m.position[0], m.position[1]) for m in (js_i, js_j))
    H_ji = np.linalg.inv(
        infinite_homography(K_i, K_j @ np.diag([f_scale, f_scale, 1.0]), relative_rotation(R_i, R_j))
    )
    gx, gy = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    pts_j = division_undistort(np.column_stack([gx.ravel(), gy.ravel()]), lam_j, K_j[:2, 2], K_j[0, 0])
    pts_i = division_distort(apply_homography(H_ji, pts_j), lam_i, K_i[:2, 2], K_i[0, 0]).reshape(H, W, 2)
    maps = pts_i.astype(np.float32)
    warped = cv2.remap(img_i.astype(np.float32), maps[..., 0], maps[..., 1], cv2.INTER_CUBIC)
    valid = np.all((pts_i > 2) & (pts_i < [W - 3, H - 3]), axis=2).astype(np.uint8)
    valid = cv2.erode(valid, np.ones((7, 7), np.uint8))
    assert valid.mean() > 0.5
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-8)
    A = np.eye(2, 3, dtype=np.float32)
    _, A = cv2.findTransformECC(img_j.astype(np.float32), warped, A, cv2.MOTION_AFFINE, criteria, valid, 3)
    ys, xs = np.nonzero(valid)
    P = np.column_stack([xs, ys]).astype(float)
    return np.linalg.norm(P @ A[:, :2].T.astype(float) + A[:, 2] - P, axis=1)


@pytest.mark.parametrize("name", ["jpeg", "mono8"])
def test_ground_truth_homography_maps_image_content(bags: dict[str, Path], name: str) -> None:
    """Features of frame i, sent through the true lens and H_ij = K_j R_j R_i^T K_i^-1, land on the same
    content in frame j (to a few hundredths of a pixel); with a 2% focal error they do not."""
    msgs = read_bag(bags[name])
    topic = "/ptz/image_raw/compressed" if name == "jpeg" else "/ptz/image_raw"
    imgs = [_gray(m) for _, m in msgs[topic]]
    infos = [m for _, m in msgs["/ptz/ground_truth/camera_info"]]
    joints = [m for _, m in msgs["/ptz/ground_truth/joint_states"]]
    for i, j in [(0, 1), (6, 7), (9, 11), (15, 18)]:
        good = _warp_residuals(imgs[i], imgs[j], infos[i], infos[j], joints[i], joints[j])
        bad = _warp_residuals(imgs[i], imgs[j], infos[i], infos[j], joints[i], joints[j], f_scale=1.02)
        print(
            f"{name} {i}->{j}: exact mean {good.mean():.4f} max {good.max():.4f}, 2% f error {bad.max():.2f}"
        )
        assert good.mean() < 0.03 and good.max() < 0.1, (i, j, good.mean(), good.max())
        assert bad.max() > 2.0, (i, j, bad.max())


def test_distortion_and_raw_format(bags: dict[str, Path]) -> None:
    msgs = read_bag(bags["mono8"])
    images = msgs["/ptz/image_raw"]
    assert len(images) == FRAMES
    m = images[0][1]
    assert (m.encoding, m.width, m.height, m.step, len(m.data)) == ("mono8", W, H, W, W * H)
    f_wide = focal_from_hfov(W, DEFAULT_HFOV)
    for _, info in msgs["/ptz/ground_truth/camera_info"]:
        assert info.distortion_model == "division" and len(info.d) == 1
        f = info.k[0]
        assert division_corner_shift(info.d[0], W, H, f) == pytest.approx(0.12 * f_wide / f, rel=1e-9)


def test_same_seed_same_bytes(bags: dict[str, Path]) -> None:
    """Same arguments and bag name (mcap stores its file name) = same bytes, with 2 threads or 1."""
    a, b = (p / "jpeg.mcap" for p in (bags["jpeg"], bags["again"]))
    assert a.read_bytes() == b.read_bytes()
    assert (bags["jpeg"] / "synth_params.yaml").read_text() == (
        bags["again"] / "synth_params.yaml"
    ).read_text()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--frames", "-5"], "--frames"),
        (["--zoom-max", "0.5"], "--zoom-max"),
        (["--fps", "0"], "--fps"),
        (["--fps", "nan"], "--fps"),
        (["--jpeg-quality", "101"], "--jpeg-quality"),
        (["--distortion", "0.9"], "--distortion"),
    ],
)
def test_absurd_options(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture,
    args: list[str],
    message: str,
) -> None:
    out = tmp_path / "bag"
    assert synth(monkeypatch, out, *args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("ptz-selfcal synth: error:") and message in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []


def test_bad_panorama_and_existing_output(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    not_image = tmp_path / "notes.jpg"
    not_image.write_text("not a jpeg")
    wrong_aspect = tmp_path / "wide.png"
    cv2.imwrite(str(wrong_aspect), np.zeros((100, 300, 3), np.uint8))
    cases = [
        (tmp_path / "missing.jpg", "no such file"),
        (not_image, "cannot read"),
        (wrong_aspect, "equirectangular"),
    ]
    for pano, message in cases:
        argv = ["synth", str(pano), str(tmp_path / "out"), "--frames", "5", "--quiet"]
        monkeypatch.setattr(sys, "argv", ["ptz-selfcal", *argv])
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("precious")
    assert synth(monkeypatch, existing) == 2
    assert "already exists" in capsys.readouterr().err
    assert [p.name for p in existing.iterdir()] == ["keep.txt"]
    assert synth(monkeypatch, tmp_path / "no" / "bag") == 2
    assert "no such directory" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing", "notes.jpg", "wide.png"]  # no leftovers


def test_cli_process_fails_cleanly(tmp_path: Path) -> None:
    """A real process: one line on stderr, exit status 2, no traceback."""
    proc = subprocess.run(
        [sys.executable, "-c", CLI, "synth", str(tmp_path / "nope.jpg"), str(tmp_path / "o")],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
    assert "no such file" in proc.stderr


def test_namespace_and_sqlite3(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "cam1"
    assert synth(monkeypatch, out, "--namespace", "/cam1", "--frames", "3", "--storage", "sqlite3") == 0
    with BagReader(out) as reader:
        names = {t.name: t.count for t in reader.topics()}
    assert names["/cam1/image_raw/compressed"] == 3 and names["/cam1/ground_truth/camera_info"] == 3
    assert all(n.startswith("/cam1/") and "/ptz/" not in n for n in names) and len(names) == 4
    assert any(p.suffix == ".db3" for p in out.iterdir())


def _synth_argv(monkeypatch: pytest.MonkeyPatch, *argv: str) -> int:
    argv = ("synth", str(PANORAMA), *argv, "--quiet")
    monkeypatch.setattr(sys, "argv", ["ptz-selfcal", *argv])
    return cli.main(list(argv))


def test_paper_configuration_is_the_papers_sequence(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--paper-config A (section 4.1): 30 frames of 640x480 mono8 at 2 fps, the principal ray on a 5 deg
    circle, f linear from 800 to 1400 px, the principal point at the image centre; all in the ground
    truth of every frame."""
    out = tmp_path / "paper_a"
    assert _synth_argv(monkeypatch, str(out), "--paper-config", "A") == 0
    msgs = read_bag(out)
    images = msgs["/ptz/image_raw"]
    assert len(images) == 30 and {(m.encoding, m.width, m.height) for _, m in images} == {("mono8", 640, 480)}
    assert [stamp_ns(m) for _, m in images] == [START_NS + i * 500_000_000 for i in range(30)]
    K = np.array([np.asarray(m.k).reshape(3, 3) for _, m in msgs["/ptz/ground_truth/camera_info"]])
    np.testing.assert_allclose(K[:, 0, 0], np.linspace(800.0, 1400.0, 30), rtol=1e-12)
    np.testing.assert_allclose(K[:, :2, 2], np.tile([319.5, 239.5], (30, 1)), atol=1e-12)
    js = [m.position for _, m in msgs["/ptz/ground_truth/joint_states"]]
    axes = np.array([ptz_rotation(p[0], p[1])[2] for p in js])  # principal ray in the world
    np.testing.assert_allclose(np.degrees(np.arccos(axes[:, 2])), 5.0, atol=1e-9)
    phase = np.unwrap(np.arctan2(-axes[:, 1], axes[:, 0]))
    np.testing.assert_allclose(np.diff(phase), 2.0 * np.pi / 30, atol=1e-9)  # once round, evenly
    params = yaml.safe_load((out / "synth_params.yaml").read_text())["profile"]
    assert (params["motion"], params["paper_config"], params["circle_radius_deg"]) == ("circle", "A", 5.0)


def test_paper_configuration_b_with_overrides(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Options given beside a preset win; B is 3.5 deg and f 1200 -> 2000 px whatever the frame count."""
    out = tmp_path / "paper_b"
    argv = ["--paper-config", "B", "--frames", "6", "--format", "jpeg", "--pp-drift", "4", "2"]
    assert _synth_argv(monkeypatch, str(out), *argv) == 0
    msgs = read_bag(out)
    assert len(msgs["/ptz/image_raw/compressed"]) == 6
    K = np.array([np.asarray(m.k).reshape(3, 3) for _, m in msgs["/ptz/ground_truth/camera_info"]])
    np.testing.assert_allclose(K[:, 0, 0], np.linspace(1200.0, 2000.0, 6), rtol=1e-12)
    np.testing.assert_allclose(K[-1, :2, 2] - K[0, :2, 2], [4.0, 2.0], atol=1e-9)  # drift at f_tele
    js = [m.position for _, m in msgs["/ptz/ground_truth/joint_states"]]
    axes = np.array([ptz_rotation(p[0], p[1])[2] for p in js])
    np.testing.assert_allclose(np.degrees(np.arccos(axes[:, 2])), 3.5, atol=1e-9)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--f-tele", "900", "--zoom-max", "2"], "not both"),
        (["--f-wide", "800", "--f-tele", "700"], "--f-tele"),
        (["--slow-start", "5"], "--slow-start"),
        (["--motion", "patrol", "--pan-cycles", "2", "--dwell", "0.3"], "dwell"),
        (["--motion", "circle", "--circle-radius-deg", "0"], "--circle-radius-deg"),
    ],
)
def test_absurd_motion_options(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture,
    args: list[str],
    message: str,
) -> None:
    assert synth(monkeypatch, tmp_path / "bag", *args) == 2  # 20 frames at 30 fps: 0.63 s long
    err = capsys.readouterr().err.strip()
    assert err.startswith("ptz-selfcal synth: error:") and message in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []
