"""The learned zoom model: monotone fit, bounded memory, atomic persistence, ROS calibration export."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

from ptz_selfcal.camera.distortion import division_lambda_for_corner_shift, division_to_plumb_bob
from ptz_selfcal.camera.geometry import intrinsic_matrix
from ptz_selfcal.persist.state_files import STATE_FILE
from ptz_selfcal.status import CalibrationStatus as S
from ptz_selfcal.zoom import model as zm
from ptz_selfcal.zoom.model import ZoomModel, ZoomModelError
from ptz_selfcal.zoom.rate import ZoomRate

W, H = 1280, 720
SRC = str(Path(__file__).resolve().parents[2] / "src" / "ptz_selfcal")


def f_true(zoom):
    """A 1x -> 3x zoom lens, close to exponential in the encoder (0 .. 1000)."""
    return 1108.0 * np.exp(np.log(3.0) * (np.asarray(zoom, dtype=float) / 1000.0) ** 1.3)


def cx_true(zoom):
    return 640.0 + 0.012 * np.asarray(zoom, dtype=float)  # the principal point drifts with zoom


def k12_true(zoom):
    f = float(f_true(zoom))
    lam = division_lambda_for_corner_shift(0.12 * 1108.0 / f, W, H, f)
    return division_to_plumb_bob(lam, intrinsic_matrix(f, float(cx_true(zoom)), 360.0), W, H)


def noisy_model(n=1500, zoom_range=(100.0, 900.0), noise_f=0.01, seed=0, **kwargs):
    rng = np.random.default_rng(seed)
    model = ZoomModel(**kwargs)
    for z in rng.uniform(*zoom_range, n):
        f = float(f_true(z)) * (1.0 + rng.normal(0.0, noise_f))
        model.add_sample(z, f, float(cx_true(z)) + rng.normal(0, 2.0), 360.0 + rng.normal(0, 2.0), -0.3, 0.1)
    return model


def test_monotone_fit_recovers_zoom_to_focal_within_one_percent():
    model = noisy_model()
    lo, hi = model.covered_range()
    assert lo == pytest.approx(100.0, abs=2.0) and hi == pytest.approx(900.0, abs=2.0)
    grid = np.linspace(lo, hi, 400)
    f = np.array([model.predict(z).K[0, 0] for z in grid])
    rel = np.abs(f / f_true(grid) - 1.0)
    assert rel.max() < 0.01 and np.median(rel) < 0.003
    assert np.all(np.diff(f) >= 0.0)  # monotone despite 1% noise per sample
    cx = np.array([model.predict(z).K[0, 2] for z in grid])
    assert np.abs(cx - cx_true(grid)).max() < 1.0
    # the reported uncertainty is of the size of the error, not zero and not wild
    sigma = np.array([model.predict(z).sigma_f for z in grid]) / f
    assert np.all(sigma > 0.0) and np.median(sigma) < 0.01
    assert np.median(rel) < 3.0 * np.median(sigma)


def test_monotone_even_when_data_are_locally_decreasing():
    model = ZoomModel()
    rng = np.random.default_rng(1)
    for z in rng.uniform(0.0, 100.0, 300):
        f = 1000.0 + 5.0 * z - (200.0 if 40.0 < z < 50.0 else 0.0)  # a glitch in the estimates
        model.add_sample(z, f, 640.0, 360.0)
    f = np.array([model.predict(z).K[0, 0] for z in np.linspace(0.0, 100.0, 500)])
    assert np.all(np.diff(f) >= -1e-9)


def test_distortion_and_principal_point_follow_zoom():
    rng = np.random.default_rng(2)
    model = ZoomModel()
    for z in rng.uniform(0.0, 1000.0, 800):
        k1, k2 = k12_true(z)
        model.add_sample(z, float(f_true(z)), float(cx_true(z)), 360.0, k1 + rng.normal(0, 0.002), k2)
    for z in (50.0, 500.0, 950.0):
        p = model.predict(z)
        k1, k2 = k12_true(z)
        assert p.D[0] == pytest.approx(k1, abs=0.01) and p.D[2:].tolist() == [0.0, 0.0, 0.0]
        assert p.K[0, 2] == pytest.approx(float(cx_true(z)), abs=0.5) and p.K[1, 1] == p.K[0, 0]


def test_bounded_memory_over_a_long_run():
    rng = np.random.default_rng(3)
    model = ZoomModel(max_bins=32)
    zooms = rng.uniform(0.0, 16384.0, 20000)
    for z in zooms:
        model.add_sample(z, 1000.0 * np.exp(z / 16384.0), 640.0, 360.0)
    assert model.bin_count <= 32 and model.sample_count == 20000
    assert model.predict(8000.0).K[0, 0] == pytest.approx(1000.0 * np.exp(8000.0 / 16384.0), rel=0.005)


def test_extrapolation_is_flagged_and_uncertain():
    model = noisy_model(n=600)
    inside = model.predict(500.0)
    outside = model.predict(1000.0)
    assert inside.in_range and not outside.in_range
    assert outside.sigma_f / outside.K[0, 0] > 3.0 * inside.sigma_f / inside.K[0, 0]
    assert outside.K[0, 0] > model.predict(900.0).K[0, 0]  # log f extended with the end slope
    # a few keyframes spread over the range: between them is inside the visited range
    sparse = ZoomModel()
    for z in np.linspace(0.0, 1000.0, 9):
        sparse.add_sample(z, float(f_true(z)), 640.0, 360.0)
    assert sparse.predict(437.0).in_range and not sparse.predict(1001.0).in_range
    assert sparse.predict(437.0).K[0, 0] == pytest.approx(float(f_true(437.0)), rel=0.01)
    with pytest.raises(ZoomModelError):
        ZoomModel().predict(10.0)
    assert not ZoomModel().add_sample(1.0, float("nan"), 640.0, 360.0)


def test_save_load_round_trip_and_restart_prediction(tmp_path):
    model = noisy_model(n=800)
    path = tmp_path / "state" / "zoom_model.yaml"
    model.save(path)
    restarted = ZoomModel.load(path)
    for z in (150.0, 420.0, 880.0):
        a, b = model.predict(z), restarted.predict(z)
        np.testing.assert_allclose(a.K, b.K, rtol=1e-12)
        assert a.sigma_f == pytest.approx(b.sigma_f, rel=1e-9) and a.in_range == b.in_range
        # a restarted calibrator starts within 1% of the true focal length at its first frame
        assert abs(b.K[0, 0] / float(f_true(z)) - 1.0) < 0.01
    assert yaml.safe_load(path.read_text())["version"] == zm.FORMAT_VERSION
    assert [p.name for p in path.parent.iterdir()] == ["zoom_model.yaml"]  # no temporary left


def test_exception_between_write_and_rename_keeps_old_file(tmp_path, monkeypatch):
    path = tmp_path / "zoom_model.yaml"
    old = noisy_model(n=200, seed=4)
    old.save(path)
    before = path.read_bytes()

    def failing_replace(src, dst):
        raise OSError("simulated crash before rename")

    monkeypatch.setattr(zm.os, "replace", failing_replace)
    with pytest.raises(OSError):
        noisy_model(n=300, seed=5).save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert ZoomModel.load(path).predict(500.0).K[0, 0] == pytest.approx(old.predict(500.0).K[0, 0])
    assert [p.name for p in tmp_path.iterdir()] == ["zoom_model.yaml"]


def test_process_killed_while_writing_leaves_old_file_loadable(tmp_path):
    """A real process is SIGKILLed halfway through writing the new model (its data already on disk)."""
    path = tmp_path / "zoom_model.yaml"
    old = noisy_model(n=200, seed=6)
    old.save(path)
    before = path.read_bytes()
    child = textwrap.dedent(
        f"""
        import os, sys, time
        sys.path.insert(0, {SRC!r})
        from ptz_selfcal.zoom import model as zm
        model = zm.ZoomModel()
        for z in range(0, 1000, 3):
            model.add_sample(float(z), 2000.0 + z, 600.0, 300.0, -0.1, 0.01)
        real_fdopen = os.fdopen

        class HalfWriter:
            def __init__(self, stream):
                self.stream = stream
            def __enter__(self):
                return self
            def __exit__(self, *exc):
                return False
            def write(self, text):
                self.stream.write(text[: len(text) // 2])
                self.stream.flush()
                os.fsync(self.stream.fileno())
                print("half written", flush=True)
                time.sleep(60)

        zm.os.fdopen = lambda fd, *a, **k: HalfWriter(real_fdopen(fd, *a, **k))
        model.save({str(path)!r})
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "half written"
        proc.kill()
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -9
    leftovers = [p for p in tmp_path.iterdir() if p.name != "zoom_model.yaml"]
    assert len(leftovers) == 1 and leftovers[0].stat().st_size > 0  # the killed writer's half file
    assert path.read_bytes() == before
    restarted, reason = ZoomModel.load_or_new(path)
    assert reason is None
    assert restarted.predict(500.0).K[0, 0] == pytest.approx(old.predict(500.0).K[0, 0])
    # the next save succeeds and cleans stale temporaries once they are old
    os.utime(leftovers[0], (0, 0))
    restarted.save(path)
    assert [p.name for p in tmp_path.iterdir()] == ["zoom_model.yaml"]


@pytest.mark.parametrize(
    "content",
    [
        "",
        "format: ptz_selfcal_zoom_model\nversion: 1\nsettings: {max_bins: 64",  # truncated
        "\x00\x01\x02 not yaml: [",
        "- just\n- a list\n",
        "format: something_else\nversion: 1\n",
        "format: ptz_selfcal_zoom_model\nversion: 99\nsettings: {}\nbins: []\n",
        "format: ptz_selfcal_zoom_model\nversion: 1\nsettings: {max_bins: 64}\nbins: []\n",
    ],
)
def test_corrupt_file_gives_zoom_model_error_and_fresh_start(tmp_path, content):
    path = tmp_path / "zoom_model.yaml"
    path.write_text(content)
    with pytest.raises(ZoomModelError):
        ZoomModel.load(path)
    model, reason = ZoomModel.load_or_new(path)
    assert model.is_empty() and reason


def test_invalid_numbers_in_a_well_formed_file(tmp_path):
    path = tmp_path / "zoom_model.yaml"
    noisy_model(n=100).save(path)
    data = yaml.safe_load(path.read_text())
    data["bins"][0]["w_log_f"] = float("nan")
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ZoomModelError, match="bin"):
        ZoomModel.load(path)
    data["bins"][0] = {"key": 0, "n": "many"}
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ZoomModelError):
        ZoomModel.load(path)
    with pytest.raises(ZoomModelError):
        ZoomModel.load(tmp_path / "missing.yaml")
    assert ZoomModel.load_or_new(tmp_path / "missing.yaml")[1] is None


def test_export_camera_calibration_yaml(tmp_path):
    model = noisy_model(n=500)
    paths = model.export_camera_calibration_yaml(tmp_path / "calib", [100, 500.5, 900], W, H, "ptz cam")
    assert [p.name for p in paths] == [
        "ptz_cam_zoom_100.yaml",
        "ptz_cam_zoom_500.5.yaml",
        "ptz_cam_zoom_900.yaml",
    ]
    for path, zoom in zip(paths, (100, 500.5, 900)):
        data = yaml.safe_load(path.read_text())
        assert list(data) == [
            "image_width",
            "image_height",
            "camera_name",
            "camera_matrix",
            "distortion_model",
            "distortion_coefficients",
            "rectification_matrix",
            "projection_matrix",
        ]
        assert (data["image_width"], data["image_height"], data["camera_name"]) == (W, H, "ptz cam")
        assert data["distortion_model"] == "plumb_bob"
        K = np.array(data["camera_matrix"]["data"]).reshape(3, 3)
        pred = model.predict(zoom)
        np.testing.assert_allclose(K, pred.K, rtol=1e-9)
        assert data["distortion_coefficients"]["rows"] == 1 and data["distortion_coefficients"]["cols"] == 5
        np.testing.assert_allclose(data["distortion_coefficients"]["data"], pred.D, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(np.array(data["rectification_matrix"]["data"]), np.eye(3).ravel())
        P = np.array(data["projection_matrix"]["data"]).reshape(3, 4)
        np.testing.assert_allclose(P, np.hstack([pred.K, np.zeros((3, 1))]), rtol=1e-9)


def test_fit_from_calibration_arrays_and_incremental_update():
    rng = np.random.default_rng(7)
    zooms = rng.uniform(0.0, 1000.0, 200)
    Ks = np.array([intrinsic_matrix(float(f_true(z)), float(cx_true(z)), 360.0) for z in zooms])
    Ds = np.tile([-0.2, 0.05, 0.0, 0.0, 0.0], (len(zooms), 1))
    model = zm.fit_zoom_model(zooms, Ks, Ds)
    assert model.ready() and not ZoomModel().ready()
    assert model.predict(500.0).K[0, 0] == pytest.approx(float(f_true(500.0)), rel=0.002)
    assert model.predict(500.0).D[0] == pytest.approx(-0.2, abs=1e-9)
    assert 0.0 < model.sigma_f(500.0) < 0.01 * float(f_true(500.0))
    before = model.sample_count
    assert model.add_calibrations(zooms[:10], Ks[:10]) == 10 and model.sample_count == before + 10
    with pytest.raises(ValueError):
        model.add_calibrations(zooms[:3], Ks[:2])


def test_uncertainty_is_unknown_rather_than_zero_without_redundancy():
    two = ZoomModel()
    two.add_sample(0.0, 1000.0, 640.0, 360.0)
    two.add_sample(100.0, 2000.0, 640.0, 360.0)
    p = two.predict(50.0)
    assert np.isnan(p.sigma_f) and 1000.0 < p.K[0, 0] < 2000.0 and p.in_range
    few = ZoomModel()
    rng = np.random.default_rng(9)
    for z in np.linspace(0.0, 1000.0, 6):
        few.add_sample(z, float(f_true(z)) * (1.0 + 0.01 * rng.normal()), 640.0, 360.0)
    assert few.sigma_f(500.0) > 0.0


def test_exact_samples_give_the_lens_law_within_a_tenth_of_a_percent():
    zooms = np.linspace(0.0, 1000.0, 40)
    model = ZoomModel()
    for z in zooms:
        model.add_sample(z, float(f_true(z)), float(cx_true(z)), 360.0, *k12_true(z))
    grid = np.linspace(0.0, 1000.0, 301)
    f = np.array([model.predict(z).K[0, 0] for z in grid])
    assert np.abs(f / f_true(grid) - 1.0).max() < 1e-3
    assert np.all(np.diff(f) > 0.0)
    assert model.predict(500.0).D[0] == pytest.approx(k12_true(500.0)[0], abs=2e-3)


def live_samples(zooms, rel_error=0.0, sigma=0.004, keys=None):
    keys = range(len(zooms)) if keys is None else keys
    return {
        k: (z, float(f_true(z)) * (1.0 + rel_error), float(cx_true(z)), 360.0, 0.0, 0.0, sigma**-2)
        for k, z in zip(keys, zooms)
    }


def test_live_samples_are_replaced_by_later_estimates_and_committed_when_dropped():
    model = ZoomModel()
    zooms = np.linspace(100.0, 900.0, 12)
    model.set_live(live_samples(zooms, rel_error=0.05))  # a first, poor solve: 5% too long
    assert model.live_count == 12 and model.bin_count == 0
    assert model.predict(500.0).K[0, 0] == pytest.approx(1.05 * float(f_true(500.0)), rel=2e-3)
    model.set_live(live_samples(zooms))  # the bundle adjustment refined them: the 5% is gone
    assert model.sample_count == 12
    assert model.predict(500.0).K[0, 0] == pytest.approx(float(f_true(500.0)), rel=2e-3)
    # keyframes 0..3 leave the calibration: their last estimates become history
    model.set_live({k: v for k, v in live_samples(zooms).items() if k >= 4})
    assert model.live_count == 8 and model.bin_count == 4 and model.sample_count == 12
    assert model.commit_live(keep=[11]) == 7 and model.live_keys() == [11]
    assert model.sample_count == 12 and model.covered_range() == pytest.approx((100.0, 900.0))
    bounded = ZoomModel(max_live=5)
    bounded.set_live(live_samples(zooms))
    assert bounded.live_count == 5 and bounded.sample_count == 12


def test_reloaded_history_is_kept_when_a_new_session_learns(tmp_path):
    """Session 1 saw the wide end, session 2 (restarted on the saved model) the tele end."""
    path = tmp_path / "zoom_model.yaml"
    first = ZoomModel()
    first.set_live(live_samples(np.linspace(0.0, 500.0, 15)))
    first.save(path)
    data = yaml.safe_load(path.read_text())
    assert len(data["live"]) == 15  # a save keeps live samples live (a restored calibration refreshes them)
    second = ZoomModel.load(path)
    assert second.commit_live() == 15  # the session restarted without that calibration: history
    second.set_live(live_samples(np.linspace(500.0, 1000.0, 15), keys=range(15)))  # ids reused
    second.set_live(live_samples(np.linspace(500.0, 1000.0, 15), keys=range(15)))  # a re-solve
    assert second.sample_count == 30 and second.covered_range() == pytest.approx((0.0, 1000.0))
    for z in (50.0, 250.0, 750.0, 950.0):
        assert second.predict(z).in_range
        assert second.predict(z).K[0, 0] == pytest.approx(float(f_true(z)), rel=3e-3)
    second.save(path)
    third = ZoomModel.load(path)
    assert third.sample_count == 30 and third.live_count == 15
    assert third.predict(250.0).K[0, 0] == pytest.approx(second.predict(250.0).K[0, 0], rel=1e-12)


def test_weights_and_robust_fit_keep_poorly_determined_keyframes_from_pulling_the_model():
    zooms = np.linspace(0.0, 1000.0, 30)
    samples = live_samples(zooms)
    # the adjustment barely constrains two keyframes (6% sigma), which are 3% off
    for k in (10, 11):
        z, f, cx, cy, k1, k2, _ = samples[k]
        samples[k] = (z, 1.03 * f, cx, cy, k1, k2, 0.06**-2)
    # and one keyframe is 4% off although it claims the usual sigma (a gross outlier)
    z, f, cx, cy, k1, k2, w = samples[20]
    samples[20] = (z, 0.96 * f, cx, cy, k1, k2, w)
    model = ZoomModel()
    model.set_live(samples)
    grid = np.linspace(0.0, 1000.0, 201)
    rel = np.abs(np.array([model.predict(z).K[0, 0] for z in grid]) / f_true(grid) - 1.0)
    assert rel.max() < 3e-3
    unweighted = ZoomModel(huber=0.0)
    unweighted.add_samples([s[:6] for s in samples.values()])
    rel_u = np.abs(np.array([unweighted.predict(z).K[0, 0] for z in grid]) / f_true(grid) - 1.0)
    assert rel_u.max() > 3.0 * rel.max()  # what the weights and the reweighting are worth


def test_uncertainty_covers_a_common_scale_error_of_one_calibration():
    """All keyframes of one calibration share its scale error (section 6.2): the model cannot average
    it away, and its sigma_f (from the samples' own sigmas) says so."""
    sigma = 0.004
    model = ZoomModel()
    model.set_live(live_samples(np.linspace(0.0, 1000.0, 30), rel_error=sigma, sigma=sigma))
    for z in (100.0, 500.0, 900.0):
        p = model.predict(z)
        err = abs(p.K[0, 0] - float(f_true(z)))
        assert err <= 2.0 * p.sigma_f and p.sigma_f < 3.0 * sigma * p.K[0, 0]


def test_invalid_live_entries_in_a_well_formed_file(tmp_path):
    path = tmp_path / "zoom_model.yaml"
    model = ZoomModel()
    model.set_live(live_samples(np.linspace(0.0, 1000.0, 8)))
    model.save(path)
    data = yaml.safe_load(path.read_text())
    data["live"][3]["n"] = 2.0
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ZoomModelError, match="live"):
        ZoomModel.load(path)
    data["live"] = {"not": "a list"}
    path.write_text(yaml.safe_dump(data))
    fresh, reason = ZoomModel.load_or_new(path)
    assert fresh.is_empty() and "live" in reason


def predicted_from_zoom(session, K, zoom) -> tuple[np.ndarray, np.ndarray]:
    """Every frame of a sweep replayed without a homography (tracking lost) at 30 frames/s: the zoom
    model's K from the frame's own encoder reading; (relative error, relative sigma_f) per frame."""
    from test_calibration_state import HEIGHT as CS_H
    from test_calibration_state import WIDTH as CS_W

    from ptz_selfcal.online import session as cs

    err, sigma = [], []
    for j, z in enumerate(zoom):
        frame = cs.FrameInput(100.0 + j / 30.0, None, "TRACKING_LOST", CS_W, CS_H, zoom=float(z))
        out = session.process(frame)
        assert out.status == S.PREDICTED_FROM_ZOOM and out.source == "zoom_model"
        err.append(out.K[1, 1] / K[j][1, 1] - 1.0)
        sigma.append(out.sigma_f / out.K[1, 1])
    return np.array(err), np.array(sigma)


# 120 frames is the sweep the model was developed on; 64, 100 and 150 are held out
@pytest.mark.parametrize("frames", [64, 100, 120, 150])
def test_zoom_model_sigma_covers_frames_predicted_from_a_lagged_noisy_encoder(tmp_path, frames):
    """The zoom encoder is not f (800 ln(f / 700) counts, 2 counts of noise, half a frame late): a
    frame predicted from its reading is off by the encoder's noise and lag and by the curve's error
    between the keyframes sampled, and its sigma_f says so: >= 95 % of the frames within 3 sigma."""
    from test_calibration_state import encoded_sweep, feed

    from ptz_selfcal.online import session as cs

    K, H, zoom = encoded_sweep(frames)
    config = cs.SessionConfig(nominal_hfov_deg=50.0)
    first = cs.CalibratorSession(config, state_dir=tmp_path)
    feed(first, H, zoom)
    first.save()
    (tmp_path / STATE_FILE).unlink()
    restarted = cs.CalibratorSession(config, state_dir=tmp_path)
    restarted.restore()
    err, sigma = predicted_from_zoom(restarted, K, zoom)
    assert np.mean(np.abs(err) <= 3.0 * sigma) >= 0.95, (np.abs(err) / sigma).max()
    assert np.median(sigma) < 0.05  # an uncertainty, not a shrug


def test_restarted_calibrator_keeps_the_saved_history_and_learns_on_top(tmp_path):
    """CalibratorSession: the saved model's samples survive a restart without the calibration state
    (a new calibration on a new reference) and the new session's keyframes are added, not refitted.
    The zoom readings are the encoder's (test_calibration_state.encoded_sweep), not f."""
    from test_calibration_state import HEIGHT as CS_H
    from test_calibration_state import WIDTH as CS_W
    from test_calibration_state import encoded_sweep, feed

    from ptz_selfcal.online import session as cs

    K, H, f = encoded_sweep(120)
    first = cs.CalibratorSession(
        cs.SessionConfig(nominal_hfov_deg=50.0),
        state_dir=tmp_path,
    )
    feed(first, H, f)
    learned = first.calibration.zoom_model.sample_count
    # the calibration's frames are live; those its bounded set dropped were committed with their last K
    live = first.calibration.zoom_model.live_count
    assert learned >= 8 and 8 <= live <= learned
    assert live == len(first.calibration.sampled_keyframes)
    first.save()
    (tmp_path / STATE_FILE).unlink()  # the calibration is not restored: a fresh one starts
    second = cs.CalibratorSession(
        cs.SessionConfig(nominal_hfov_deg=50.0),
        state_dir=tmp_path,
    )
    messages = second.restore()
    assert any("loaded zoom model" in m for m in messages), messages
    assert (
        second.calibration.zoom_model.live_count == 0
        and second.calibration.zoom_model.sample_count == learned
    )
    # first frame after the restart, tracking lost: K from the saved model within 1% and its 3 sigma
    out = second.process(cs.FrameInput(0.0, None, "TRACKING_LOST", CS_W, CS_H, zoom=float(f[60])))
    assert out.status == S.PREDICTED_FROM_ZOOM and abs(out.K[0, 0] / K[60][0, 0] - 1.0) < 0.01
    assert abs(out.K[0, 0] - K[60][0, 0]) <= 3.0 * out.sigma_f
    feed(second, H, f)
    assert second.calibration.zoom_model.sample_count >= learned + 8  # history plus the new calibration
    model = second.calibration.zoom_model
    assert 8 <= model.live_count <= model.sample_count - learned
    total = second.calibration.zoom_model.sample_count
    replay = copy.deepcopy(second)  # the sweep again without homographies: K from the zoom encoder
    err, sigma = predicted_from_zoom(replay, K, f)
    assert np.mean(np.abs(err) <= 3.0 * sigma) >= 0.95 and np.median(np.abs(err)) < 0.005
    second.process(cs.FrameInput(9.0, H[5], "TRACKING", CS_W, CS_H, keyframe_id=0, reference_id="other"))
    second.step(0.0, paced=False)  # a new reference: the calibration is reset, its keyframes become history
    assert (
        second.calibration.zoom_model.live_count == 0 and second.calibration.zoom_model.sample_count == total
    )


def test_each_calibration_has_its_own_scale_error_levelled_where_they_overlap():
    """Session 1 calibrated well (-0.2%, sigma 0.15%) but saw the tele end only through a few poor
    keyframes; session 2 saw everything with a 1.4% scale error (sigma 0.6%): its offset, measured where
    the two overlap, is removed at the tele end too (section 6.2: one scale error per calibration)."""

    def sessions(model, separate):
        model.set_live(live_samples(np.linspace(0.0, 600.0, 20), rel_error=-0.002, sigma=0.0015))
        if separate:
            model.new_calibration()
        else:
            model.commit_live()
        model.set_live(live_samples(np.linspace(0.0, 1000.0, 30), rel_error=0.014, sigma=0.006))
        return model

    grid = np.linspace(0.0, 1000.0, 201)
    levelled = sessions(ZoomModel(), separate=True)
    pooled = sessions(ZoomModel(), separate=False)
    err = np.abs([levelled.predict(z).K[0, 0] / float(f_true(z)) - 1.0 for z in grid])
    err_pooled = np.abs([pooled.predict(z).K[0, 0] / float(f_true(z)) - 1.0 for z in grid])
    assert err.max() < 4e-3 and err_pooled.max() > 0.01
    assert levelled.calibration == 1 and levelled.sample_count == 50
    # the offsets survive a save and a reload
    again = ZoomModel.from_dict(yaml.safe_load(yaml.safe_dump(levelled.to_dict())))
    assert again.predict(900.0).K[0, 0] == pytest.approx(levelled.predict(900.0).K[0, 0], rel=1e-9)


def test_old_calibrations_merge_with_their_offsets_bounded_memory():
    model = ZoomModel(max_calibrations=2)
    assert model.new_calibration() == 0  # nothing learned yet: no new calibration
    for k, err in enumerate((0.003, -0.004, 0.002, -0.001)):
        model.set_live(live_samples(np.linspace(100.0 * k, 600.0 + 100.0 * k, 15), rel_error=err))
        model.new_calibration()
    assert len({b["calibration"] for b in model.to_dict()["bins"]}) <= 2 and model.sample_count == 60
    grid = np.linspace(0.0, 900.0, 91)
    err = np.abs([model.predict(z).K[0, 0] / float(f_true(z)) - 1.0 for z in grid])
    assert err.max() < 4e-3


def test_encoder_lag_is_learned_from_zooming_in_and_out():
    """The encoder reads the zoom of 40 ms earlier: zooming in, f is longer than the reading says,
    zooming out shorter. The model learns the lag that joins both branches and predicts from the
    reading and its rate; without it the same samples leave errors of the zoom speed times the lag."""
    lag, period = 0.04, 10.0

    def zoom_true(t):
        return 500.0 * (1.0 - np.cos(2.0 * np.pi * t / period))

    def reading(t):  # encoder value and its rate (counts / s) at image time t
        return zoom_true(t - lag), 500.0 * 2.0 * np.pi / period * np.sin(2.0 * np.pi * (t - lag) / period)

    t_key = np.linspace(0.2, 9.8, 30)
    z_enc, rate = reading(t_key)
    samples = {
        k: (z_enc[k], float(f_true(zoom_true(t_key[k]))), 640.0, 360.0, 0.0, 0.0, 0.002**-2, rate[k])
        for k in range(len(t_key))
    }
    model, plain = ZoomModel(), ZoomModel(estimate_lag=False)
    model.set_live(samples)
    plain.set_live(samples)
    assert model.lag == pytest.approx(lag, abs=0.005) and plain.lag == 0.0
    t = np.linspace(0.5, 9.5, 200)
    z, r = reading(t)
    truth = f_true(zoom_true(t))
    err = np.abs([model.predict(a, b).K[0, 0] for a, b in zip(z, r)] / truth - 1.0)
    err_plain = np.abs([plain.predict(a, b).K[0, 0] for a, b in zip(z, r)] / truth - 1.0)
    assert err.max() < 2e-3 and err_plain.max() > 4e-3
    again = ZoomModel.from_dict(yaml.safe_load(yaml.safe_dump(model.to_dict())))
    assert again.lag == model.lag
    assert again.predict(z[50], r[50]).K[0, 0] == pytest.approx(model.predict(z[50], r[50]).K[0, 0], rel=1e-9)
    # a restarted calibration refreshes the restored keyframes without knowing their rates (NaN):
    # they keep the ones they were saved with (and the lag)
    again.set_live({k: (*v[:7], float("nan")) for k, v in samples.items()})
    assert [e["rate"] for e in again.to_dict()["live"]] == pytest.approx(list(rate))
    assert again.lag == pytest.approx(lag, abs=0.005)
    # zooming one way only: no lag is claimed
    one_way = ZoomModel()
    one_way.set_live({k: v for k, v in samples.items() if rate[k] > 0})
    assert one_way.lag == 0.0


def test_zoom_rate_from_frame_encoder_values():
    rates = ZoomRate()
    t = np.arange(0.0, 1.0, 1.0 / 30.0)
    z = 100.0 + 600.0 * t
    z[10] = z[9]  # an encoder value held for one frame
    out = [rates.update(a, b) for a, b in zip(t, z)]
    assert out[0] == 0.0 and out[1] == pytest.approx(600.0)
    assert np.all(np.abs(np.array(out[15:]) - 600.0) < 1e-6)  # a straight line once the glitch is out
    assert min(out[9:15]) > 450.0 and max(out[9:15]) < 750.0  # smoothed (a difference gives 0, 1200)
    assert rates.update(1.05, float("nan")) == 0.0
    assert rates.update(3.0, 900.0) == 0.0  # after a gap nothing is known
