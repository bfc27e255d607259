"""`ptz-selfcal mosaic --images DIR` end to end: a folder of stills rendered from the repository's
panorama (a hand-held 360 degree set of one lens, in name order) -> the stills front end and the
calibrator session -> PNG mosaic in the frame of the first still.

The mosaic must show the source panorama where it is covered: the source seen through the first
still's true orientation, compared at the mosaic's resolution, feature by feature (the issue's at most
one mosaic pixel) and grey level by grey level after one global gain. A file that is not an image is
skipped and counted; a missing or empty folder and a folder without two readable images are errors.
"""

from __future__ import annotations

import math
import re
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SOURCE_PANORAMA, cli_command

from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation
from ptz_selfcal.mosaic.projection import Projection, mosaic_width
from ptz_selfcal.sim.render import build_panorama, panorama_coordinates, render_view

SIZE = (320, 400)  # portrait, as a hand-held set
F = 0.5 * SIZE[0] / math.tan(math.radians(16.0))  # 32 degrees across, 20 degree steps
N_STILLS = 18
MAX_WIDTH = 2048


def _cli(*args: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    return subprocess.run(cli_command(*args), capture_output=True, text=True, timeout=timeout)


def _rotations(seed: int = 4) -> np.ndarray:
    """A pan 15 degrees below the horizon (the textured ground) with a hand's tilt and roll."""
    rng = np.random.default_rng(seed)
    pan = np.radians(360.0 * np.arange(N_STILLS) / N_STILLS + rng.uniform(-1.0, 1.0, N_STILLS))
    tilt = np.radians(-15.0 + rng.uniform(-2.0, 2.0, N_STILLS))
    roll = np.radians(rng.uniform(-1.0, 1.0, N_STILLS))
    return np.array([ptz_rotation(p, t, r) for p, t, r in zip(pan, tilt, roll, strict=True)])


@pytest.fixture(scope="module")
def stills(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """(folder of colour JPEG stills and one file that is not an image, true world -> camera R)."""
    folder = tmp_path_factory.mktemp("stills")
    pano = build_panorama(cv2.imread(str(SOURCE_PANORAMA), cv2.IMREAD_COLOR))
    K = intrinsic_matrix(F, 0.5 * (SIZE[0] - 1), 0.5 * (SIZE[1] - 1))
    R = _rotations()
    for i, Ri in enumerate(R):
        cv2.imwrite(
            str(folder / f"still_{i:02d}.jpg"), render_view(pano, K, Ri, SIZE), [cv2.IMWRITE_JPEG_QUALITY, 95]
        )
    (folder / "still_05b.jpg").write_bytes(b"not a JPEG")  # among the good ones
    (folder / "notes.txt").write_text("not an image name: not tried")
    return folder, R


def _source_in_frame(R0: np.ndarray, projection: Projection) -> np.ndarray:
    """The source panorama as a mosaic in the frame of a camera with world -> camera rotation R0."""
    source = cv2.imread(str(SOURCE_PANORAMA), cv2.IMREAD_COLOR)
    W, H = projection.width, projection.height
    source = cv2.resize(source, (W, H), interpolation=cv2.INTER_AREA)  # both at the mosaic's resolution
    gx, gy = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    rays = projection.rays_of_pixels(np.column_stack([gx.ravel(), gy.ravel()])) @ R0  # R0^T d: world
    x, y = panorama_coordinates(rays.T.reshape(3, H, W).astype(np.float32), W, H)
    wrapped = cv2.copyMakeBorder(source, 0, 0, 4, 4, cv2.BORDER_WRAP)
    return cv2.remap(wrapped, np.mod(x, W) + 4, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def test_mosaic_of_a_folder_of_stills(stills: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    folder, R = stills
    out = tmp_path / "stills.png"
    proc = _cli("mosaic", "--images", str(folder), "--out", str(out), "--max-width", str(MAX_WIDTH))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert re.search(rf"mosaic: {N_STILLS} of {N_STILLS + 1} stills placed", proc.stdout), proc.stdout
    assert "skipped: unreadable 1;" in proc.stdout and "still_05b.jpg: not a readable image" in proc.stderr
    f = float(re.search(r"f ([\d.]+) px", proc.stdout).group(1))
    assert abs(f / F - 1.0) < 0.005
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape == (MAX_WIDTH // 2, MAX_WIDTH, 4)  # 2 pi f is above the cap
    assert mosaic_width(F, MAX_WIDTH) == MAX_WIDTH
    covered = image[:, :, 3] == 255
    assert covered.any(axis=0).all()  # a full turn: every longitude
    truth = _source_in_frame(R[0], Projection.spherical(MAX_WIDTH))
    mask = cv2.erode(covered.astype(np.uint8), np.ones((7, 7), np.uint8))
    a = cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2GRAY)
    b = cv2.cvtColor(truth, cv2.COLOR_BGR2GRAY)
    # geometry: SIFT features of the mosaic matched to the source's, median displacement <= 1 px
    sift = cv2.SIFT_create(nfeatures=3000)
    ka, da = sift.detectAndCompute(a, mask)
    kb, db = sift.detectAndCompute(b, mask)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.75 * p[1].distance]
    shift = np.linalg.norm(
        np.array([ka[g.queryIdx].pt for g in good]) - np.array([kb[g.trainIdx].pt for g in good]), axis=1
    )
    assert len(good) > 200 and np.mean(shift < 5.0) > 0.9, (len(good), np.median(shift))
    assert np.median(shift) < 1.0, np.median(shift)
    # photometry over the covered region after one global gain (exposure compensation, blending)
    va, vb = a[mask > 0].astype(float), b[mask > 0].astype(float)
    gain = float((va * vb).sum() / (va * va).sum())
    assert np.median(np.abs(gain * va - vb)) < 8.0


def test_folder_errors(stills: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    out = str(tmp_path / "x.png")
    missing = _cli("mosaic", "--images", str(tmp_path / "nowhere"), "--out", out)
    assert missing.returncode == 2 and "no such folder" in missing.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("no images here")
    proc = _cli("mosaic", "--images", str(empty), "--out", out)
    assert proc.returncode == 2 and "no image files" in proc.stderr
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "a.jpg").write_bytes(b"\xff\xd8 broken")
    (bad / "b.png").write_bytes(b"")
    (bad / "c.jpg").write_bytes((stills[0] / "still_00.jpg").read_bytes())  # one good still alone
    proc = _cli("mosaic", "--images", str(bad), "--out", out)
    assert proc.returncode == 2 and "1 readable image(s) of 3" in proc.stderr, proc.stderr
    assert "a.jpg: not a readable image" in proc.stderr and "b.png: not a readable image" in proc.stderr
    assert not Path(out).exists()
    both = _cli("mosaic", str(tmp_path), "--images", str(empty), "--out", out)
    assert both.returncode == 2 and "either IN_BAG or --images" in both.stderr
