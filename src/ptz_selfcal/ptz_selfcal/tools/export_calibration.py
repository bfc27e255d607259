"""`ptz-selfcal export-calibration STATE_DIR --out DIR`: the saved zoom model as camera_calibration YAML.

One file per zoom setting, in the format camera_calibration writes and camera_calibration_parsers
reads (K, plumb_bob D, R = I, P = [K | 0]), so that a tool that wants a fixed calibration per preset
can take the self-calibrated one. The zoom settings are given, or spread over the zoom range the
model has seen; the image size comes from the saved calibration state unless given.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ptz_selfcal.persist.state_files import STATE_FILE, ZOOM_MODEL_FILE, StateFileError, load_yaml_file
from ptz_selfcal.tools.cli import CliError
from ptz_selfcal.zoom import ZoomModel, ZoomModelError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("state_dir", type=Path, help="the calibrator's state_dir (holds zoom_model.yaml)")
    parser.add_argument("--out", type=Path, required=True, help="directory for the YAML files")
    parser.add_argument("--zoom", type=float, nargs="+", help="zoom encoder values to export")
    parser.add_argument(
        "--count", type=int, default=5, help="without --zoom: this many values spread over the seen range"
    )
    parser.add_argument("--camera-name", default="ptz", help="camera_name written into the files")
    parser.add_argument("--size", type=int, nargs=2, metavar=("WIDTH", "HEIGHT"), help="image size")


def run(args: argparse.Namespace) -> int:
    path = args.state_dir / ZOOM_MODEL_FILE
    try:
        model = ZoomModel.load(path)
    except ZoomModelError as exc:
        raise CliError(str(exc)) from exc
    limits = model.covered_range()
    if model.is_empty() or limits is None:
        raise CliError(f"{path}: the zoom model has no calibration yet")
    if args.zoom:
        zooms = [float(z) for z in args.zoom]
    else:
        if not 1 <= args.count <= 1000:
            raise CliError(f"--count must be in [1, 1000], got {args.count}")
        zooms = [float(z) for z in np.linspace(limits[0], limits[1], args.count)]
    width, height = args.size if args.size else _image_size(args.state_dir)
    outside = [z for z in zooms if not limits[0] <= z <= limits[1]]
    if outside:
        print(f"export-calibration: zoom {outside} outside the seen range {limits}: extrapolated")
    try:
        written = model.export_camera_calibration_yaml(args.out, zooms, width, height, args.camera_name)
    except (ZoomModelError, ValueError, np.linalg.LinAlgError) as exc:
        raise CliError(f"the zoom model does not predict: {exc}") from exc
    for zoom, file in zip(zooms, written):
        print(f"zoom {zoom:g}: {file}")
    return 0


def _image_size(state_dir: Path) -> tuple[int, int]:
    path = state_dir / STATE_FILE
    try:
        data = load_yaml_file(path)
    except StateFileError as exc:
        raise CliError(f"{exc}; give the image size with --size") from exc
    size = None if data is None else data.get("image_size")
    if not size:
        raise CliError(f"{path}: no image size saved; give it with --size WIDTH HEIGHT")
    return int(size[0]), int(size[1])
