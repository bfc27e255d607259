"""camera_info_manager's habits: a camera_info_url's calibration file, and which K a calibrator accepts.

The file is camera_calibration's YAML (what `cameracalibrator` and `ptz-selfcal export-calibration`
write, zoom/camera_calibration.py): image size, camera_matrix K, plumb_bob distortion. The URL is a
file:// URL or a plain path, with camera_info_manager's ${NAME} substitution (the camera's name).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.persist.state_files import read_yaml_mapping

Array = NDArray[np.float64]


class CameraInfoFileError(Exception):
    """A camera_info_url that cannot be used: unsupported URL, unreadable file, unusable calibration."""


@dataclass(frozen=True)
class CameraCalibration:
    """One fixed calibration: K (3x3, K[2, 2] = 1) and plumb_bob D (5) of images width x height."""

    K: Array
    D: Array
    width: int
    height: int
    camera_name: str = ""


def camera_info_path(url: str, camera_name: str = "") -> Path | None:
    """The file a camera_info_url names; None for "" (no file)."""
    url = url.strip().replace("${NAME}", camera_name)
    if not url:
        return None
    if "://" not in url:
        return Path(url).expanduser()
    parsed = urlparse(url)
    if parsed.scheme != "file":
        raise CameraInfoFileError(f"camera_info_url {url!r}: only file:// URLs and plain paths are supported")
    return Path(unquote(parsed.netloc + parsed.path))


def read_camera_calibration(path: str | os.PathLike[str]) -> CameraCalibration:
    """The calibration in a camera_calibration YAML file; CameraInfoFileError when it is unusable."""
    path = Path(path)
    data = read_yaml_mapping(path, CameraInfoFileError, "camera_calibration YAML mapping")
    try:
        width, height = int(data["image_width"]), int(data["image_height"])
        K = _matrix(data["camera_matrix"], 3, 3)
        D = np.zeros(5)
        if data.get("distortion_coefficients") is not None:
            d = np.asarray(data["distortion_coefficients"]["data"], dtype=float).ravel()
            D[: min(5, d.size)] = d[:5]
    except (KeyError, TypeError, ValueError) as exc:
        raise CameraInfoFileError(
            f"{path}: not a camera_calibration file ({type(exc).__name__}: {exc})"
        ) from exc
    model = data.get("distortion_model", "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial") or not np.all(np.isfinite(D)):
        raise CameraInfoFileError(f"{path}: distortion model {model!r} is not plumb_bob")
    reason = intrinsics_problem(K, (width, height))
    if reason:
        raise CameraInfoFileError(f"{path}: {reason}")
    return CameraCalibration(K / K[2, 2], D, width, height, str(data.get("camera_name") or ""))


def _matrix(entry: dict, rows: int, cols: int) -> Array:
    values = np.asarray(entry["data"], dtype=float).ravel()
    if values.size != rows * cols:
        raise ValueError(f"{values.size} values for a {rows}x{cols} matrix")
    return values.reshape(rows, cols)


def intrinsics_problem(
    K: Array, size: tuple[int, int], image_size: tuple[int, int] | None = None
) -> str | None:
    """Why K of images `size` cannot be a calibration of the images of `image_size` (None: unknown
    yet), or None when it can: K must be finite and upper triangular with a positive diagonal (its dual
    image of the absolute conic K K^T positive definite; K = 0 is ROS's "uncalibrated")."""
    K = np.asarray(K, dtype=float)
    width, height = int(size[0]), int(size[1])
    if width <= 0 or height <= 0:
        return f"image size {width}x{height} is not an image size"
    if image_size is not None and (width, height) != tuple(image_size):
        return f"image size {width}x{height} differs from the images' {image_size[0]}x{image_size[1]}"
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        return "K is not a finite 3x3 matrix"
    if not np.any(K):
        return "K = 0 (an uncalibrated camera)"
    if K[2, 2] <= 0.0:
        return f"K[2, 2] = {K[2, 2]:g} is not positive"
    K = K / K[2, 2]
    if max(abs(K[1, 0]), abs(K[2, 0]), abs(K[2, 1])) > 1e-9 * max(abs(K[0, 0]), 1.0):
        return "K is not upper triangular"
    if not (K[0, 0] > 0.0 and K[1, 1] > 0.0):
        return f"K is not positive definite (fx = {K[0, 0]:g}, fy = {K[1, 1]:g})"
    if not math.isfinite(float(np.linalg.cond(K))) or abs(K[0, 1]) > K[0, 0]:
        return "K is degenerate"
    return None
