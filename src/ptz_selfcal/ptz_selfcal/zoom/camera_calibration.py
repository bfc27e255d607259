"""The camera_calibration export: per-zoom calibration files in the camera_calibration_parsers YAML
format, so that ROS tools can use the zoom model's K and D at fixed zoom settings."""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.persist.atomic_file import atomic_write_text

Array = NDArray[np.float64]


def write_camera_calibrations(
    directory: str | os.PathLike[str],
    calibrations: Iterable[tuple[float, Array, Array]],
    width: int,
    height: int,
    camera_name: str,
) -> list[Path]:
    """One calibration file per (zoom, K, D), written atomically, named by camera and zoom."""
    out_dir = Path(directory)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for zoom, K, D in calibrations:
        text = camera_calibration_yaml(K, D, width, height, camera_name)
        path = out_dir / f"{_safe_name(camera_name)}_zoom_{_safe_name(f'{float(zoom):g}')}.yaml"
        atomic_write_text(path, text)
        paths.append(path)
    return paths


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", text)


def _matrix_yaml(name: str, rows: int, cols: int, data: Array) -> str:
    values = ", ".join(f"{float(v):.10g}" for v in np.asarray(data, dtype=float).ravel())
    return f"{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{values}]\n"


def camera_calibration_yaml(K: Array, D: Array, width: int, height: int, camera_name: str) -> str:
    """The text camera_calibration / camera_calibration_parsers write (R = I, P = [K | 0])."""
    K = np.asarray(K, dtype=float)
    P = np.hstack([K, np.zeros((3, 1))])
    return (
        f"image_width: {int(width)}\n"
        f"image_height: {int(height)}\n"
        f"camera_name: {camera_name}\n"
        + _matrix_yaml("camera_matrix", 3, 3, K)
        + "distortion_model: plumb_bob\n"
        + _matrix_yaml("distortion_coefficients", 1, 5, np.asarray(D, dtype=float).ravel()[:5])
        + _matrix_yaml("rectification_matrix", 3, 3, np.eye(3))
        + _matrix_yaml("projection_matrix", 3, 4, P)
    )
