"""Shared pytest fixtures: ROS environment per test module, node processes, short synthetic bags.

Nothing here is autouse: a test asks for what it needs. Node tests set a module-level ROS_DOMAIN_ID
(each test file its own) and use `ros_env`, which exports it (and LOCALHOST discovery) for the test's
own rclpy and returns the environment for the node processes it starts.

Imagery: `SOURCE_PANORAMA` is the repository's own panorama (bags/source, CC BY-SA); a test that truly
needs the shared data (../shared/data beside the repository) asks for the `shared_data` fixture, and
the run lists those tests. The run fails when more than MAX_SKIPPED tests are skipped, and
PTZ_TEST_SEED=<int> runs the modules, and the tests inside each, in a seeded random order.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# The repository's own CC BY-SA panorama (bags/README.md): what the synth helpers render from.
SOURCE_PANORAMA = REPO / "bags" / "source" / "examplepano.jpg"
# Optional shared panoramas beside the repository (../shared), for the few tests that need another scene.
PANORAMAS = Path(os.environ.get("PTZ_PANORAMAS", REPO.parent / "shared" / "data" / "panoramas"))
PYTHON = sys.executable
SOURCE_PANORAMA = REPO / "bags/source/examplepano.jpg"
SHARED_DATA = REPO.parent / "shared" / "data"  # CI lays shared/ beside its clone, as here
MAX_SKIPPED = 5
_skipped: list[str] = []
_shared_data_users: list[str] = []


@pytest.fixture
def ros_env(
    request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, str]:
    """LOCALHOST discovery and the test module's ROS_DOMAIN_ID, for this process and its children; a
    ROS_HOME of the test's own (`launch` keeps a camera's state there by default: no test reads another
    test's, or the user's ~/.ros); the shipped Fast DDS profile, which every node gets from launch and
    run (Fast DDS reads it when a process's first participant starts)."""
    from ptz_selfcal.tools.launch import PROFILE_VARIABLES, default_profile_file

    domain = getattr(request.module, "ROS_DOMAIN_ID", None)
    if domain is None:
        pytest.fail("a test using ros_env must set a module-level ROS_DOMAIN_ID")
    values = {
        "ROS_DOMAIN_ID": str(domain),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "PYTHONUNBUFFERED": "1",
        "RCUTILS_COLORIZED_OUTPUT": "0",
        "ROS_HOME": str(tmp_path_factory.mktemp("ros_home")),
        PROFILE_VARIABLES[0]: str(default_profile_file()),
    }
    for key, value in values.items():
        monkeypatch.setenv(key, value)
    return dict(os.environ)


class NodeProcess:
    """A child process (node, launch, run) with its output in a file; stop() = SIGINT, wait, kill."""

    def __init__(self, cmd: Sequence[str], env: dict[str, str], log_dir: Path, name: str) -> None:
        self.cmd = list(cmd)
        self.log_path = log_dir / f"{name}.log"
        self._log = open(self.log_path, "w+b")  # noqa: SIM115 (closed in stop)
        self.proc = subprocess.Popen(self.cmd, env=env, stdout=self._log, stderr=subprocess.STDOUT)
        self.returncode: int | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait_for_output(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return True
            if not self.alive():
                return text in self.output()
            time.sleep(0.05)
        return False

    def wait(self, timeout: float) -> int | None:
        try:
            self.returncode = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        return self.returncode

    def stop(self, timeout: float = 10.0, sig: int = signal.SIGINT) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5.0)
        self.returncode = self.proc.returncode
        self._log.close()
        return self.returncode


@pytest.fixture
def start_process(tmp_path: Path) -> Iterator[Callable[..., NodeProcess]]:
    """start_process(cmd, env, name) -> NodeProcess; every process still running is stopped at teardown."""
    started: list[NodeProcess] = []

    def start(cmd: Sequence[str], env: dict[str, str], name: str = "proc") -> NodeProcess:
        proc = NodeProcess(cmd, env, tmp_path, f"{name}-{len(started)}")
        started.append(proc)
        return proc

    yield start
    for proc in started:
        if proc.alive():
            proc.stop(timeout=5.0)


def node_command(module: str, *ros_args: str) -> list[str]:
    return [PYTHON, "-m", module, "--ros-args", *ros_args]


def cli_command(*args: str) -> list[str]:
    """The `ptz-selfcal` entry point, independent of whether its console script is installed."""
    return [PYTHON, "-c", "import sys; from ptz_selfcal.tools.cli import main; sys.exit(main())", *args]


def make_synth_bag(out: Path, frames: int, width: int, height: int, *extra: str) -> Path:
    """A bag from `ptz-selfcal synth` of the repository's panorama (fails, never skips: both ship here)."""
    cmd = cli_command(
        "synth", str(SOURCE_PANORAMA), str(out), "--frames", str(frames), "--width", str(width),
        "--height", str(height), "--quiet", *extra,
    )  # fmt: skip
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    if result.returncode != 0:
        pytest.fail(f"synth failed: {result.stderr.strip()}")
    return out


# A lens the calibrator's shipped prior does not know: 47 deg at the wide end (the prior's 60 deg is 25 %
# short in f), the principal point 20 px off centre, a 10x lens behind the nonlinear zoom encoder, which
# reports 50 ms late with 3 counts of noise.
SHORT_SYNTH_LENS = (
    "--hfov", "47", "--pp-offset", "-12", "16", "--lens-ratio", "10", "--zoom-noise", "3",
    "--encoder-lag", "0.05", "--seed", "11",
)  # fmt: skip


@pytest.fixture(scope="session")
def short_synth_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """40 JPEG frames of 640x360 with encoders and ground truth (about 3 s to make), SHORT_SYNTH_LENS."""
    return make_synth_bag(tmp_path_factory.mktemp("synth") / "short", 40, 640, 360, *SHORT_SYNTH_LENS)


@pytest.fixture
def scratch_dir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="ptz_selfcal_test_") as tmp:
        yield Path(tmp)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared data directory beside the repository (skipped, and counted, when it is absent)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data {SHARED_DATA} absent")
    return SHARED_DATA


def shared_data_file(relative: str) -> Path:
    """A file of the shared data for code that is not a test's fixture (a harness, a cached loader): the
    running test is listed among the shared-data users, and skipped (counted) when the file is absent."""
    current = os.environ.get("PYTEST_CURRENT_TEST", "").rsplit(" ", 1)[0]
    if current and current not in _shared_data_users:
        _shared_data_users.append(current)
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"shared data file {path} absent")
    return path


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """PTZ_TEST_SEED: shuffle the modules, and the tests within each (module fixtures stay built once)."""
    seed = os.environ.get("PTZ_TEST_SEED")
    if not seed:
        return
    rng = random.Random(int(seed))
    modules: dict[str, list[pytest.Item]] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::")[0], []).append(item)
    order = list(modules.values())
    rng.shuffle(order)
    for group in order:
        rng.shuffle(group)
    items[:] = [item for group in order for item in group]


def pytest_report_header(config: pytest.Config) -> str:
    seed = os.environ.get("PTZ_TEST_SEED")
    return f"ptz_selfcal: test order {'shuffled, PTZ_TEST_SEED=' + seed if seed else 'as collected'}"


def pytest_runtest_call(item: pytest.Item) -> None:
    if "shared_data" in getattr(item, "fixturenames", ()) and item.nodeid not in _shared_data_users:
        _shared_data_users.append(item.nodeid)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.skipped and not hasattr(report, "wasxfail"):
        _skipped.append(report.nodeid)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if len(_skipped) > MAX_SKIPPED and exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    """Which tests need the shared data, and how many were skipped (more than MAX_SKIPPED fails)."""
    write = terminalreporter.write_line
    write(f"tests that need the shared data ({SHARED_DATA}): {len(_shared_data_users)}")
    for nodeid in _shared_data_users:
        write(f"  {nodeid}")
    write(f"skipped tests: {len(_skipped)} (at most {MAX_SKIPPED})")
    if len(_skipped) > MAX_SKIPPED:
        write(f"FAILED: more than {MAX_SKIPPED} tests skipped", red=True, bold=True)
