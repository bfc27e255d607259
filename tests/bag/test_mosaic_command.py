"""`ptz-selfcal mosaic` end to end: a short synthetic bag -> run (real nodes over DDS) -> PNG mosaic.

The mosaic must be the size its longest focal length asks for (or the cap), 2:1 when spherical, and
cover what the camera saw: the footprints of the ground-truth views (K and pan/tilt of synth) of the
frames it places, since the command levels the mosaic with the encoders. By default it places every
tracked frame (through the final calibration), with --calibration published the calibrated ones.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import cli_command, make_synth_bag

from ptz_selfcal.camera.geometry import ptz_rotation
from ptz_selfcal.mosaic.blend import Accumulator
from ptz_selfcal.mosaic.projection import Projection, mosaic_width
from ptz_selfcal.mosaic.warp import Box, FrameView, footprint, footprint_box, warp_frame
from ptz_selfcal.tools import evaluate
from ptz_selfcal.tools import mosaic as mosaic_tool

ROS_DOMAIN_ID = 197
FRAMES, WIDTH, HEIGHT = 30, 320, 180
SYNTH = ("--pan-amplitude", "25", "--tilt-amplitude", "5", "--zoom-max", "1.5", "--seed", "5")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(ROS_DOMAIN_ID))
    return env


def _cli(*args: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    return subprocess.run(cli_command(*args), env=_env(), capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(input bag, output bag of `ptz-selfcal run --with-images`: it holds the images too)."""
    root = tmp_path_factory.mktemp("mosaic")
    in_bag = make_synth_bag(root / "in", FRAMES, WIDTH, HEIGHT, *SYNTH)
    out_bag = root / "out"
    proc = _cli("run", str(in_bag), "--out", str(out_bag), "--quiet", "--deterministic", "--with-images")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return in_bag, out_bag


def _calibrated(data: evaluate.BagData) -> set[int]:
    """Stamps of the frames the command places by default: a valid orientation, a calibrated status."""
    return {
        stamp
        for stamp, f in data.frame_calibration.items()
        if np.any([f.orientation.x, f.orientation.y, f.orientation.z, f.orientation.w])
        and f.status in mosaic_tool.CALIBRATED_STATUS
    }


def _tracked(out_bag: Path) -> set[int]:
    """Stamps of the frames the command places by default: a homography from the tracker."""
    return {stamp for stamp, t in mosaic_tool.read_homographies(out_bag).items() if t.H is not None}


def _truth_coverage(out_bag: Path, projection: Projection, placed: set[int]) -> np.ndarray:
    """Where the ground-truth views (synth's K, pan and tilt) of the placed frames land on a surface."""
    data = evaluate.read_output_bag(out_bag)
    acc = Accumulator(projection, Box(0, projection.width, 0, projection.height), 1)
    for stamp, info in sorted(data.gt_camera_info.items()):
        if stamp not in placed:
            continue
        js = data.gt_joint_states[stamp]
        pan, tilt = (js.position[list(js.name).index(n)] for n in ("pan", "tilt"))
        K = np.asarray(info.k, dtype=float).reshape(3, 3)
        view = FrameView(K, (0.0, 0.0, 0.0), ptz_rotation(pan, tilt), WIDTH, HEIGHT)
        box = footprint_box(footprint(view), projection)
        acc.add(warp_frame(np.ones((HEIGHT, WIDTH), np.float32), view, projection, box))
    assert len(data.gt_camera_info) == FRAMES
    return acc.image()[:, :, 3] > 0


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def _placed(stdout: str) -> int:
    match = re.search(r"mosaic: (\d+) frames placed", stdout)
    assert match, stdout
    return int(match.group(1))


def test_mosaic_of_an_output_bag(bags: tuple[Path, Path], tmp_path: Path) -> None:
    """The default: every tracked frame, the frames published before the first solve included."""
    out_bag = bags[1]
    out = tmp_path / "pano.png"
    proc = _cli("mosaic", str(out_bag), "--out", str(out), "--quiet")  # the images from the output bag
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = evaluate.read_output_bag(out_bag)
    tracked = _tracked(out_bag)
    assert len(tracked - _calibrated(data)) > 0  # frames published before the first solve
    assert _placed(proc.stdout) == len(tracked) > FRAMES // 2
    untracked = FRAMES - len(tracked)
    assert (f"not tracked {untracked}" in proc.stdout) == (untracked > 0), proc.stdout
    # one mosaic pixel per image pixel at the longest focal length (the true one: within 2 %)
    f_max = max(float(info.k[0]) for stamp, info in data.gt_camera_info.items() if stamp in tracked)
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape[1] == 2 * image.shape[0]
    assert abs(image.shape[1] / mosaic_width(f_max, 8192) - 1.0) < 0.02
    covered = image[:, :, 3] > 0
    truth = _truth_coverage(out_bag, Projection.spherical(image.shape[1]), tracked)
    assert truth.shape == covered.shape
    assert _iou(covered, truth) > 0.9
    # the pixels hold the scene: not a constant, no black holes inside the covered region
    inner = cv2.erode(covered.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    assert image[:, :, :3][inner].std() > 20 and (image[:, :, :3][inner].max(axis=1) > 0).all()


def test_published_calibration_places_the_calibrated_frames(bags: tuple[Path, Path], tmp_path: Path) -> None:
    out_bag = bags[1]
    out = tmp_path / "published.png"
    proc = _cli("mosaic", str(out_bag), "--out", str(out), "--quiet", "--calibration", "published")
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = evaluate.read_output_bag(out_bag)
    valid = {
        stamp
        for stamp, f in data.frame_calibration.items()
        if np.any([f.orientation.x, f.orientation.y, f.orientation.z, f.orientation.w])
    }
    calibrated = _calibrated(data)
    invalid, uncalibrated = FRAMES - len(valid), len(valid) - len(calibrated)
    assert len(calibrated) > FRAMES // 2
    assert _placed(proc.stdout) == len(calibrated)
    assert (f"invalid orientation {invalid}" in proc.stdout) == (invalid > 0), proc.stdout
    assert (f"not calibrated {uncalibrated}" in proc.stdout) == (uncalibrated > 0), proc.stdout
    # one mosaic pixel per image pixel at the longest published focal length of the frames placed
    f_max = max(float(info.k[0]) for stamp, info in data.camera_info.items() if stamp in calibrated)
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape == (mosaic_width(f_max, 8192) // 2, mosaic_width(f_max, 8192), 4)
    truth = _truth_coverage(out_bag, Projection.spherical(image.shape[1]), calibrated)
    assert _iou(image[:, :, 3] > 0, truth) > 0.9


def test_cylindrical_mosaic_covers_the_same_longitudes(bags: tuple[Path, Path], tmp_path: Path) -> None:
    in_bag, out_bag = bags
    out = tmp_path / "cyl.png"
    args = ("--input-bag", str(in_bag), "--out", str(out), "--projection", "cylindrical", "--quiet")
    proc = _cli("mosaic", str(out_bag), *args, "--max-width", "1500")
    assert proc.returncode == 0, proc.stderr[-3000:]
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape[1] == 1500 and image.shape[0] < 750
    covered = image[:, :, 3] > 0
    # the cylinder's rows span the latitudes seen: about the truth's, through the same tan(lat) law
    truth = _truth_coverage(out_bag, Projection.spherical(1500), _tracked(out_bag))
    lat = (0.5 - (np.nonzero(truth.any(axis=1))[0][[0, -1]] + 0.5) / 750) * math.pi
    expected_rows = 1500 / (2 * math.pi) * (math.tan(lat[0]) - math.tan(lat[1]))
    assert abs(image.shape[0] - expected_rows) < 0.1 * expected_rows
    assert _iou(covered.any(axis=0), truth.any(axis=0)) > 0.9  # the same longitudes
    rows = np.nonzero(covered.any(axis=1))[0]  # from the highest to the lowest view (pixel centres)
    assert rows[0] <= 1 and rows[-1] >= image.shape[0] - 2


def test_mosaic_of_an_input_bag_runs_the_nodes(bags: tuple[Path, Path], tmp_path: Path) -> None:
    in_bag, out_bag = bags
    out = tmp_path / "capped.png"
    proc = _cli("mosaic", str(in_bag), "--out", str(out), "--max-width", "1024", "--quiet", "--deterministic")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert _placed(proc.stdout) > FRAMES // 2
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape == (512, 1024, 4)  # 2 pi f is far above the cap
    truth = _truth_coverage(out_bag, Projection.spherical(1024), _tracked(out_bag))
    assert _iou(image[:, :, 3] > 0, truth) > 0.9
    assert math.isclose(image.shape[1] / image.shape[0], 2.0)


def test_eval_mosaic_beside_its_source_panorama(bags: tuple[Path, Path], tmp_path: Path) -> None:
    """eval's mosaic step: the mosaic in the panorama's frame (ground truth), next to the same region
    of the panorama the bag was rendered from (found by its synth_params.yaml name and sha256)."""
    in_bag, out_bag = bags
    data = evaluate.read_output_bag(
        out_bag, evaluate.BagData(image_stamps=evaluate.read_image_stamps(in_bag))
    )
    entry = mosaic_tool.eval_mosaic(data, out_bag, in_bag, tmp_path, max_width=1024)
    assert entry["frame"] == "ground truth" and entry["frames_placed"] == len(_tracked(out_bag))
    assert entry["source_panorama"] == "examplepano.jpg"
    mosaic = cv2.imread(entry["file"], cv2.IMREAD_UNCHANGED)
    beside = cv2.imread(entry["comparison_file"], cv2.IMREAD_COLOR)
    assert mosaic.shape == (512, 1024, 4)
    rows = np.nonzero((mosaic[:, :, 3] > 0).any(axis=1))[0]
    assert beside.shape[0] == 2 * (rows[-1] + 1 - rows[0])  # the covered rows, then the same of the source
    assert entry["photometric_median_abs_diff"] < 8.0
    # a bag without ground truth or a panorama: the mosaic levelled by the encoders, no comparison
    data.gt_joint_states.clear()
    entry = mosaic_tool.eval_mosaic(data, out_bag, in_bag, tmp_path / "plain", max_width=512)
    assert entry["frame"] == "encoders" and "comparison_file" not in entry
