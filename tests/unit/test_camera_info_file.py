"""camera_info_url's file: what the exporter writes reads back; URLs; the K a calibrator refuses, and why."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ptz_selfcal.camera.geometry import intrinsic_matrix
from ptz_selfcal.persist.camera_info_file import (
    CameraInfoFileError,
    camera_info_path,
    intrinsics_problem,
    read_camera_calibration,
)
from ptz_selfcal.zoom.camera_calibration import camera_calibration_yaml

K = intrinsic_matrix(1450.0, 652.0, 348.5)


def test_the_exporters_file_reads_back(tmp_path: Path) -> None:
    D = np.array([-0.12, 0.03, 0.0, 0.0, 0.0])
    path = tmp_path / "cam.yaml"
    path.write_text(camera_calibration_yaml(K, D, 1280, 720, "cam1"))
    calibration = read_camera_calibration(path)
    np.testing.assert_allclose(calibration.K, K)
    np.testing.assert_allclose(calibration.D, D)
    assert (calibration.width, calibration.height, calibration.camera_name) == (1280, 720, "cam1")


def test_urls_and_paths() -> None:
    assert camera_info_path("") is None
    assert camera_info_path("file:///var/cal/${NAME}.yaml", "cam1") == Path("/var/cal/cam1.yaml")
    assert camera_info_path("/var/cal/a b.yaml") == Path("/var/cal/a b.yaml")
    assert camera_info_path("file:///var/cal/a%20b.yaml") == Path("/var/cal/a b.yaml")
    with pytest.raises(CameraInfoFileError, match="only file://"):
        camera_info_path("package://ptz/cal.yaml")


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("image_width: [", "unreadable"),
        ("- 1\n- 2\n", "not a camera_calibration YAML mapping"),
        ("image_width: 1280\nimage_height: 720\n", "not a camera_calibration file"),
        (
            "image_width: 1280\nimage_height: 720\n"
            "camera_matrix: {rows: 3, cols: 3, data: [0, 0, 0, 0, 0, 0, 0, 0, 0]}\n",
            "uncalibrated",
        ),
    ],
)
def test_unusable_files_say_why(tmp_path: Path, text: str, reason: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(CameraInfoFileError, match=reason):
        read_camera_calibration(path)
    with pytest.raises(CameraInfoFileError, match="unreadable"):
        read_camera_calibration(tmp_path / "missing.yaml")


def test_which_k_is_refused() -> None:
    assert intrinsics_problem(K, (1280, 720), (1280, 720)) is None
    assert intrinsics_problem(K, (1280, 720)) is None  # no image seen yet
    assert "differs from the images" in intrinsics_problem(K, (640, 360), (1280, 720))
    assert "not an image size" in intrinsics_problem(K, (0, 0))
    negative = K.copy()
    negative[0, 0] = -negative[0, 0]
    assert "positive definite" in intrinsics_problem(negative, (1280, 720))
    lower = K.copy()
    lower[1, 0] = 3.0
    assert "upper triangular" in intrinsics_problem(lower, (1280, 720))
    nan = K.copy()
    nan[0, 2] = np.nan
    assert "finite" in intrinsics_problem(nan, (1280, 720))
    assert intrinsics_problem(2.0 * K, (1280, 720)) is None  # homogeneous: K[2, 2] scales it
