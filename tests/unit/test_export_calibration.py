"""`ptz-selfcal export-calibration`: the saved zoom model as camera_calibration YAML, read back by a
parser of that format (the keys and matrix layout camera_calibration_parsers reads)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from test_zoom_model import f_true, live_samples

from ptz_selfcal.persist.state_files import STATE_FILE, ZOOM_MODEL_FILE
from ptz_selfcal.tools import cli
from ptz_selfcal.zoom import ZoomModel


def parse_camera_calibration(text: str) -> dict:
    """camera_calibration_parsers' YAML: sizes, name, and rows x cols matrices stored row-major."""
    data = yaml.safe_load(text)

    def matrix(name: str) -> np.ndarray:
        entry = data[name]
        values = np.asarray(entry["data"], dtype=float)
        assert values.size == entry["rows"] * entry["cols"], name
        return values.reshape(entry["rows"], entry["cols"])

    return {
        "width": int(data["image_width"]),
        "height": int(data["image_height"]),
        "name": data["camera_name"],
        "model": data["distortion_model"],
        "K": matrix("camera_matrix"),
        "D": matrix("distortion_coefficients"),
        "R": matrix("rectification_matrix"),
        "P": matrix("projection_matrix"),
    }


@pytest.fixture
def state_dir(tmp_path):
    model = ZoomModel()
    model.set_live(live_samples(np.linspace(100.0, 900.0, 12)))
    model.save(tmp_path / ZOOM_MODEL_FILE)
    (tmp_path / STATE_FILE).write_text(yaml.safe_dump({"version": 1, "image_size": [1280, 720]}))
    return tmp_path, model


def test_each_zoom_gets_a_file_with_the_models_calibration(state_dir, tmp_path, capsys) -> None:
    directory, model = state_dir
    out = tmp_path / "export"
    assert (
        cli.main(["export-calibration", str(directory), "--out", str(out), "--zoom", "150", "500", "850"])
        == 0
    )
    files = sorted(out.glob("*.yaml"))
    assert len(files) == 3 and all(f.name.startswith("ptz_zoom_") for f in files)
    for zoom in (150.0, 500.0, 850.0):
        (file,) = [f for f in files if f.name == f"ptz_zoom_{zoom:g}.yaml"]
        cal = parse_camera_calibration(file.read_text())
        K, D, _, _ = model.predict(zoom)
        assert (cal["width"], cal["height"], cal["name"], cal["model"]) == (1280, 720, "ptz", "plumb_bob")
        np.testing.assert_allclose(cal["K"], K, rtol=1e-9)
        assert abs(cal["K"][0, 0] / float(f_true(zoom)) - 1.0) < 0.01  # the model, not a copy of the input
        np.testing.assert_allclose(cal["D"].ravel(), np.asarray(D).ravel()[:5], atol=1e-9)
        np.testing.assert_array_equal(cal["R"], np.eye(3))
        np.testing.assert_allclose(cal["P"], np.hstack([cal["K"], np.zeros((3, 1))]), rtol=1e-12)
    assert "zoom 500:" in capsys.readouterr().out


def test_without_zoom_values_the_seen_range_is_spread(state_dir, tmp_path) -> None:
    directory, model = state_dir
    out = tmp_path / "export"
    args = ["export-calibration", str(directory), "--out", str(out), "--count", "4", "--camera-name", "cam 1"]
    assert cli.main(args) == 0
    files = sorted(out.glob("*.yaml"))
    assert len(files) == 4 and all(f.name.startswith("cam_1_zoom_") for f in files)
    focal = sorted(parse_camera_calibration(f.read_text())["K"][0, 0] for f in files)
    low, high = model.covered_range()
    assert focal[0] == pytest.approx(model.predict(low).K[0, 0]) and focal[-1] == pytest.approx(
        model.predict(high).K[0, 0]
    )


def test_no_model_is_a_one_line_error(tmp_path, capsys) -> None:
    assert cli.main(["export-calibration", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot read zoom model" in err[0]
    assert not (tmp_path / "x").exists()
