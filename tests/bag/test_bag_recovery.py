"""A truncated, summary-less or tail-damaged bag is read up to its last complete record: the readers
return exactly the messages written before the damage, and `run`, `eval` and `play` process every
readable frame (a CameraInfo for each) and say how much was lost."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import pytest
from conftest import cli_command, make_synth_bag

from ptz_selfcal import topics
from ptz_selfcal.tools.bagio import BagReader, header_stamp_ns

ROS_DOMAIN_ID = 120
FRAMES = 24
IMAGES = topics.bag_topic(topics.IMAGE_COMPRESSED)
CAMERA_INFO = topics.bag_topic(topics.CAMERA_INFO)
MAGIC = b"\x89MCAP0\r\n"


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("recovery")
    return {
        storage: make_synth_bag(root / storage, FRAMES, 320, 180, "--storage", storage)
        for storage in ("mcap", "sqlite3")
    }


def _all_messages(bag: Path) -> list[tuple[str, int, bytes]]:
    with BagReader(bag) as reader:
        assert reader.damage is None
        return [(m.topic, m.timestamp_ns, m.raw) for m in reader.messages()]


def _copy(bag: Path, dest: Path) -> tuple[Path, Path]:
    shutil.copytree(bag, dest)
    return dest, next(p for p in dest.iterdir() if p.suffix in (".mcap", ".db3"))


def _truncated(bag: Path, dest: Path, fraction: float) -> tuple[Path, int]:
    dest, storage = _copy(bag, dest)
    cut = int(storage.stat().st_size * fraction)
    os.truncate(storage, cut)
    return dest, cut


def _before_cut(bag: Path, cut: int) -> list[tuple[str, int, bytes]]:
    """The messages of an intact (uncompressed) mcap bag whose bytes all lie before `cut`: found in the
    file independently of the reader under test."""
    data = next(bag.glob("*.mcap")).read_bytes()
    out, pos = [], 0
    for msg in _all_messages(bag):
        at = data.find(msg[2], pos)
        assert at >= 0
        pos = at + len(msg[2])
        if pos <= cut:
            out.append(msg)
    return out


def _data_section(storage: Path) -> bytes:
    """The mcap file up to and including its DataEnd record (no summary, no footer)."""
    data = storage.read_bytes()
    pos = len(MAGIC)
    while True:
        op, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        pos += 9 + length
        if op == 0x0F:
            return data[:pos]


@pytest.mark.parametrize("fraction", [0.3, 0.6, 0.9])
def test_truncated_mcap_gives_every_message_before_the_cut(
    bags: dict[str, Path], tmp_path: Path, fraction: float
) -> None:
    bag, cut = _truncated(bags["mcap"], tmp_path / "cut", fraction)
    expected = _before_cut(bags["mcap"], cut)
    images = sum(1 for m in expected if m[0] == IMAGES)
    assert 0 < images < FRAMES
    with BagReader(bag) as reader:
        got = [(m.topic, m.timestamp_ns, m.raw) for m in reader.messages()]
        assert got == expected
        assert {t.name: t.count for t in reader.topics()}[IMAGES] == images
        assert reader.unread(IMAGES) == FRAMES - images
        assert reader.start_ns == expected[0][1]
        assert reader.damage is not None and "File end magic is invalid" in reader.damage
        assert f"{IMAGES} {FRAMES - images} of {FRAMES}" in reader.damage


@pytest.mark.parametrize("footer", [True, False], ids=["footer-no-summary", "no-footer"])
def test_mcap_without_summary_reads_whole(bags: dict[str, Path], tmp_path: Path, footer: bool) -> None:
    bag, storage = _copy(bags["mcap"], tmp_path / "nosummary")
    data = _data_section(storage)
    if footer:  # a footer whose summary offsets are 0: the writer wrote no summary section
        data += b"\x02" + struct.pack("<Q", 20) + struct.pack("<QQI", 0, 0, 0) + MAGIC
    storage.write_bytes(data)
    with BagReader(bag) as reader:
        assert [(m.topic, m.timestamp_ns, m.raw) for m in reader.messages()] == _all_messages(bags["mcap"])
        assert reader.unread(IMAGES) == 0


def test_mcap_without_metadata_yaml(bags: dict[str, Path], tmp_path: Path) -> None:
    """A recording that died before writing metadata.yaml: the storage file alone is read."""
    bag, cut = _truncated(bags["mcap"], tmp_path / "nometa", 0.6)
    (bag / "metadata.yaml").unlink()
    expected = _before_cut(bags["mcap"], cut)
    for path in (bag, next(bag.glob("*.mcap"))):
        with BagReader(path) as reader:
            assert [(m.topic, m.timestamp_ns, m.raw) for m in reader.messages()] == expected
            assert reader.unread(IMAGES) is None  # nothing says how many were written


@pytest.mark.parametrize("fraction", [0.3, 0.6, 0.9])
def test_sqlite3_with_damaged_tail_reads_its_head(
    bags: dict[str, Path], tmp_path: Path, fraction: float
) -> None:
    full = _all_messages(bags["sqlite3"])
    bag, _ = _truncated(bags["sqlite3"], tmp_path / "cut", fraction)
    with BagReader(bag) as reader:
        got = [(m.topic, m.timestamp_ns, m.raw) for m in reader.messages()]
        assert reader.damage is not None and "malformed" in reader.damage
        images = sum(1 for m in got if m[0] == IMAGES)
        assert reader.unread(IMAGES) == FRAMES - images
    assert got == full[: len(got)]  # a prefix: nothing reordered, nothing made up
    # rows live in pages in insertion order: all but the last page or two before the cut are readable
    assert len(got) >= (fraction - 0.15) * len(full), (len(got), len(full))


def _run(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(cli_command(*args), env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    return proc


def _stamps(bag: Path, topic: str) -> set[int]:
    with BagReader(bag) as reader:
        return {header_stamp_ns(m.raw) for m in reader.messages([topic])}


@pytest.mark.parametrize("damage", ["cut-0.3", "cut-0.9", "no-summary"])
def test_run_gives_a_camera_info_for_every_readable_frame(
    bags: dict[str, Path], tmp_path: Path, ros_env: dict[str, str], damage: str
) -> None:
    if damage == "no-summary":
        bag, storage = _copy(bags["mcap"], tmp_path / "in")
        storage.write_bytes(_data_section(storage))
        readable = _all_messages(bags["mcap"])
    else:
        bag, cut = _truncated(bags["mcap"], tmp_path / "in", float(damage.split("-")[1]))
        readable = _before_cut(bags["mcap"], cut)
    frames = {header_stamp_ns(m[2]) for m in readable if m[0] == IMAGES}
    proc = _run(["run", str(bag), "--out", str(tmp_path / "out"), "--quiet"], ros_env)
    assert _stamps(tmp_path / "out", CAMERA_INFO) >= frames
    lost = FRAMES - len(frames)
    assert f"{len(frames)}/{len(frames)} images got a CameraInfo" in proc.stderr
    assert (f"{lost} images unreadable" in proc.stderr) == (lost > 0), proc.stderr[-2000:]


def test_eval_of_a_truncated_bag_reports_the_lost_frames(
    bags: dict[str, Path], tmp_path: Path, ros_env: dict[str, str]
) -> None:
    bag, cut = _truncated(bags["mcap"], tmp_path / "in", 0.6)
    frames = {header_stamp_ns(m[2]) for m in _before_cut(bags["mcap"], cut) if m[0] == IMAGES}
    out = tmp_path / "report"
    proc = _run(["eval", str(bag), "--out-dir", str(out), "--quiet", "--no-plots", "--with-images"], ros_env)
    report = json.loads((out / "report.json").read_text())
    assert report["frames"]["input"] == len(frames)
    assert report["frames"]["unreadable_in_input"] == FRAMES - len(frames)
    assert report["coverage"] == 1.0
    assert f"{FRAMES - len(frames)} frames unreadable" in proc.stdout
    assert _stamps(out / "output_bag", CAMERA_INFO) >= frames
    assert _stamps(out / "output_bag", IMAGES) == frames  # --with-images copied what was readable


def test_play_publishes_every_readable_message(
    bags: dict[str, Path], tmp_path: Path, ros_env: dict[str, str]
) -> None:
    bag, cut = _truncated(bags["mcap"], tmp_path / "in", 0.6)
    readable = _before_cut(bags["mcap"], cut)
    proc = _run(["play", str(bag), "--rate", "0"], ros_env)
    assert f"play: published {len(readable)} messages" in proc.stderr
    assert f"({len(_all_messages(bags['mcap'])) - len(readable)} lost)" in proc.stderr
