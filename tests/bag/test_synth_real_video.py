"""`ptz-selfcal synth`'s real-video options (issue 16): off by default, the moving mask's topic and its
exactness, the photometric steps as stated, bad values refused."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from ptz_selfcal import topics
from ptz_selfcal.sim.nuisances import EXPOSURE_GAINS
from ptz_selfcal.tools import cli
from ptz_selfcal.tools.bagio import BagReader, deserialize

PANORAMA = Path(__file__).resolve().parents[2] / "bags" / "source" / "examplepano.jpg"
W, H, FRAMES, FPS = 240, 136, 12, 10.0
BASE = ["--frames", str(FRAMES), "--width", str(W), "--height", str(H), "--fps", str(FPS), "--quiet"]
MASK = topics.bag_topic(topics.GT_MOVING_MASK)


def synth(monkeypatch: pytest.MonkeyPatch, out: Path, *extra: str) -> int:
    argv = ["synth", str(PANORAMA), str(out), *BASE, *extra]
    monkeypatch.setattr(sys, "argv", ["ptz-selfcal", *argv])
    return cli.main(argv)


def frames(path: Path) -> dict[str, list[tuple[int, np.ndarray]]]:
    """topic -> [(header stamp ns, mono8 pixels)] of every raw Image topic."""
    out: dict[str, list[tuple[int, np.ndarray]]] = {}
    with BagReader(path) as reader:
        for m in reader.messages():
            if m.msgtype != "sensor_msgs/msg/Image":
                continue
            msg = deserialize(m.raw, m.msgtype)
            assert msg.encoding == "mono8" and (msg.width, msg.height) == (W, H)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            out.setdefault(m.topic, []).append((stamp, np.asarray(msg.data, np.uint8).reshape(H, W)))
    return out


def test_the_options_off_leave_the_bag_byte_identical(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    assert synth(monkeypatch, tmp_path / "a" / "bag") == 0
    off = ["--moving-objects", "0", "--exposure-steps", "0", "--vignetting", "0", "--rolling-shutter", "0"]
    assert synth(monkeypatch, tmp_path / "b" / "bag", *off) == 0
    for name in ("bag.mcap", "synth_params.yaml"):
        assert (tmp_path / "a" / "bag" / name).read_bytes() == (tmp_path / "b" / "bag" / name).read_bytes()
    with BagReader(tmp_path / "a" / "bag") as reader:
        assert MASK not in {t.name for t in reader.topics()}


def test_the_moving_mask_is_exactly_where_the_objects_are(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Same seed with and without objects: the frames differ exactly on the mask (the noise is the
    frame's own stream, the same in both); one mask per image, same stamp."""
    raw = ["--format", "mono8", "--seed", "3"]
    period = (FRAMES - 1) / FPS
    objects = ["--moving-objects", "3", "--follow-target", "0", f"{period:g}"]
    assert synth(monkeypatch, tmp_path / "plain", *raw) == 0
    assert synth(monkeypatch, tmp_path / "objects", *raw, *objects) == 0
    plain, seen = frames(tmp_path / "plain"), frames(tmp_path / "objects")
    image_topic = topics.bag_topic(topics.IMAGE_RAW)
    assert len(seen[MASK]) == len(seen[image_topic]) == FRAMES
    for (t_img, a), (t_img2, b), (t_mask, mask) in zip(plain[image_topic], seen[image_topic], seen[MASK]):
        assert t_img == t_img2 == t_mask
        assert set(np.unique(mask)) <= {0, 255} and mask.mean() > 0.1 * 255  # the followed target at least
        on = mask > 0
        assert np.array_equal(a[~on], b[~on])
        assert np.mean(a[on] != b[on]) > 0.8  # texture over a different background


def test_exposure_steps_scale_the_frames_by_the_stated_gains(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    quiet = ["--format", "mono8", "--image-noise", "0", "--brightness-drift", "0"]
    assert synth(monkeypatch, tmp_path / "plain", *quiet) == 0
    assert synth(monkeypatch, tmp_path / "steps", *quiet, "--exposure-steps", "0.3") == 0
    image_topic = topics.bag_topic(topics.IMAGE_RAW)
    pairs = zip(frames(tmp_path / "plain")[image_topic], frames(tmp_path / "steps")[image_topic])
    for i, ((_, a), (_, b)) in enumerate(pairs):
        gain = EXPOSURE_GAINS[int(np.floor(i / FPS / 0.3)) % len(EXPOSURE_GAINS)]
        unsaturated = a.astype(float) * gain < 250
        ratio = b[unsaturated].mean() / a[unsaturated].mean()
        assert ratio == pytest.approx(gain, rel=0.01)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--moving-objects", "-1"], "--moving-objects"),
        (["--follow-target", "0.5", "0.2"], "--follow-target"),
        (["--follow-target", "0", "99"], "--follow-target"),
        (["--exposure-steps", "-1"], "--exposure-steps"),
        (["--vignetting", "1.5"], "--vignetting"),
        (["--rolling-shutter", "0.5"], "--rolling-shutter"),
    ],
)
def test_absurd_real_video_options(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture,
    args: list[str],
    message: str,
) -> None:
    assert synth(monkeypatch, tmp_path / "bag", *args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []
