"""`ptz-selfcal launch`: start the node suite as separate processes and supervise it (no ros2 launch here).

Each node (frame_ingest, homography_tracker, calibrator) runs as `python -m ptz_selfcal.nodes.<name>
--ros-args -r __node:=<name> [-r __ns:=NS] --params-file FILE [-r FROM:=TO ...]`. Their output is
prefixed with the node name. A node that dies unexpectedly is restarted with exponential backoff
(counted and logged); a node that exits with status 2 (its configuration error) or with an error status
within its first seconds (e.g. it cannot be imported) stops the suite with that node's message.
Ctrl-C/SIGTERM stops every child cleanly: SIGINT, wait, then SIGTERM and SIGKILL after timeouts; the
supervisor exits 0. Children get SIGTERM from the kernel if
the supervisor itself is killed (PR_SET_PDEATHSIG), so no orphan survives it.

With Fast DDS the nodes load the package's profile, config/fastdds.xml (dds_profile_environment; run,
the ROS launch file and the tests use the same): a shared-memory segment large enough for raw images
(the middleware's default one is smaller than one 1280x720 bgr8 image, whose fragments then overrun it
and wait for the reliable protocol's repair) and a short participant lease. A node killed outright
(kill -9, a crash) cannot say goodbye: its DDS endpoints stay matched until its participant's lease
expires (Fast DDS: 20 s), and frames published meanwhile go to the dead reader while the other nodes'
wait-for-subscriber checks count it as there; the profile's lease is 2 s (--dds-lease: a copy with
another). A profile file the environment names already is used instead (the user's configuration
wins), and launch says that the project's transport settings are then the user's to carry over. With
static peers (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and ROS_STATIC_PEERS: a suite across hosts) the
nodes get a copy with the peers as its discovery and the range SYSTEM_DEFAULT, the same discovery
without the second UDPv4 transport rmw_fastrtps adds under LOCALHOST (each datagram would go twice).

The parameter file is checked before anything starts: YAML, a mapping of node keys (a node name, or
/ns/name, /**/name, /**) to {ros__parameters: {...}}. What each node gets (name, namespace, parameters,
remappings) is decided by one pure function, plan_suite(), which the ROS launch file
(launch/ptz_selfcal.launch.py) calls too, so the two start the same graph: a plain node-name key applies
in any namespace, a homography_tracker without a state_dir of its own gets the calibrator's (a restarted
tracker reloads its keyframe map), and camera_name (the diagnostics' hardware_id) comes from the
argument, else the file, else the namespace's last component (/cam1: cam1). The nodes sit in the
camera's namespace, /ptz unless --namespace names another (topics.py). A calibrator without a state_dir
keeps its state in $ROS_HOME/ptz_selfcal/<camera_name> (--no-persist: none), so a restarted suite
starts calibrated; run and eval start fresh unless their parameter file names a state_dir.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from ptz_selfcal.tools.cli import CliError

NODE_MODULES = {
    "frame_ingest": "ptz_selfcal.nodes.frame_ingest",
    "homography_tracker": "ptz_selfcal.nodes.homography_tracker",
    "calibrator": "ptz_selfcal.nodes.calibrator",
    "mosaic": "ptz_selfcal.nodes.mosaic_node",
}
# the suite a launch starts; the live mosaic (selfcal/mosaic) is optional, off by default
SUITE_NODES = ("frame_ingest", "homography_tracker", "calibrator")
CONFIG_ERROR_STATUS = 2  # nodes exit with this status on a configuration error
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
PROFILE_FILE = "fastdds.xml"  # in config/, beside the parameter file


def shipped_config(name: str) -> Path:
    """config/<name>: from the package's share directory in the ament index (a colcon or other ament
    install, wherever its prefix is), else from the source tree (a development checkout), else from this
    Python's prefix (a pip install puts the share files there)."""
    source = Path(__file__).resolve().parents[2] / "config" / name
    candidates = [source, Path(sys.prefix) / "share" / "ptz_selfcal" / "config" / name]
    try:
        from ament_index_python.packages import get_package_share_directory

        share = Path(get_package_share_directory("ptz_selfcal"))
        candidates.insert(0, share / "config" / name)
    except (ImportError, LookupError, OSError):  # not installed with ament, or no AMENT_PREFIX_PATH
        pass
    return next((path for path in candidates if path.exists()), source)


def default_params_file() -> Path:
    """config/ptz_selfcal.yaml, the shipped parameter file (shipped_config)."""
    return shipped_config("ptz_selfcal.yaml")


def default_profile_file() -> Path:
    """config/fastdds.xml, the shipped Fast DDS profile (shipped_config)."""
    return shipped_config(PROFILE_FILE)


# ---------------------------------------------------------------------------------------------------------
# parameter files


def load_params_file(path: str | os.PathLike[str], known_nodes: Sequence[str]) -> dict[str, Any]:
    """Read and check a ROS parameter YAML file; CliError with a one-line reason otherwise."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise CliError(f"{path}: cannot read parameter file ({exc.strerror or exc})") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        raise CliError(f"{path}: not valid YAML{line}") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise CliError(f"{path}: expected a mapping of node names to {{ros__parameters: ...}}")
    for key, section in data.items():
        name = str(key).rstrip("/").rsplit("/", 1)[-1]
        if name not in known_nodes and name not in ("*", "**"):
            raise CliError(f"{path}: unknown node {key!r} (known: {', '.join(known_nodes)})")
        if not isinstance(section, dict) or "ros__parameters" not in section:
            raise CliError(f"{path}: section {key!r} must contain ros__parameters")
        params = section["ros__parameters"]
        if params is None:
            section["ros__parameters"] = {}
        elif not isinstance(params, dict):
            raise CliError(f"{path}: {key}.ros__parameters must be a mapping")
        else:
            _check_values(path, str(key), params)
    return data


def _check_values(path: Path, prefix: str, params: dict[str, Any]) -> None:
    for name, value in params.items():
        where = f"{prefix}.{name}"
        if isinstance(value, dict):
            _check_values(path, where, value)
        elif isinstance(value, list):
            kinds = {type(v) for v in value}
            if len(kinds) > 1 and kinds != {int, float}:
                raise CliError(f"{path}: {where} mixes value types in a list")
            if any(isinstance(v, dict | list) or v is None for v in value):
                raise CliError(f"{path}: {where} must be a list of plain values")
        elif value is None:
            raise CliError(f"{path}: {where} has no value")


@dataclass(frozen=True)
class NodeLaunch:
    """One node of the suite as both launchers start it: executable/module, fully qualified place,
    parameters (flat dotted names) and remappings."""

    name: str  # node name, also its executable in lib/ptz_selfcal
    module: str  # python -m module
    namespace: str  # absolute
    parameters: dict[str, Any]
    remappings: tuple[tuple[str, str], ...]

    @property
    def fully_qualified_name(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.name}"


def _key_matches(key: str, fqn: str) -> bool:
    """Whether a parameter-file key (rcl's: a node name, /ns/name, with * for one and ** for any number
    of name components) applies to the node of fully qualified name fqn."""
    import re

    key = key if key.startswith("/") else f"/**/{key}"
    pattern = ""
    for part in key.strip("/").split("/"):
        if part == "**":
            pattern += "(/[^/]+)*"
        else:
            pattern += "/" + re.escape(part).replace(r"\*", "[^/]+")
    return re.fullmatch(pattern, fqn) is not None


def _flat(params: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, value in params.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{name}."))
        else:
            out[f"{prefix}{name}"] = value
    return out


def plan_suite(
    data: dict[str, Any],
    namespace: str | None = None,
    remaps: Sequence[str] = (),
    camera_name: str | None = None,
    nodes: Sequence[str] = SUITE_NODES,
    modules: dict[str, str] | None = None,
    name_from_namespace: bool = True,
    state_root: str | None = None,
) -> list[NodeLaunch]:
    """The node suite to start, pure: `data` is a checked parameter file (load_params_file), namespace and
    remaps (FROM:=TO) as given by the user (checked here). Each node gets the sections of the file that
    match it, in file order, so later sections win as in rcl. name_from_namespace False: a private
    namespace (run's) does not name the camera. With state_root (launch: state_root()), a calibrator
    without a state_dir persists in state_root/<camera name> (per camera, as camera_info_manager keeps
    its files under ROS_HOME)."""
    from ptz_selfcal import topics

    ns = check_namespace(namespace) or topics.NAMESPACE
    pairs = tuple(tuple(r.split(":=", 1)) for r in check_remaps(remaps))
    modules = {**NODE_MODULES, **(modules or {})}
    params = {
        name: {
            k: v
            for key, section in data.items()
            if _key_matches(str(key), f"{ns}/{name}")
            for k, v in _flat(section.get("ros__parameters") or {}).items()
        }
        for name in NODE_MODULES
    }
    calibrator = params["calibrator"]
    tracker = params["homography_tracker"]
    named = camera_name or next((p["camera_name"] for p in params.values() if p.get("camera_name")), None)
    if not named:  # the camera's namespace names it; a private one (run's) does not: the default's then
        named = (ns if name_from_namespace else topics.NAMESPACE).rsplit("/", 1)[-1]
    for p in params.values():
        p["camera_name"] = named
    if state_root and not calibrator.get("state_dir"):
        calibrator["state_dir"] = str(Path(state_root) / named)
    # Not with estimate_distortion (unless a fixed lens): the lens correction's state is not persisted,
    # so a tracker that kept its reference would leave the restored calibration without corrected
    # homographies; a new map re-initialises both (zoom model meanwhile). A fixed lens saves its one
    # coefficient with the calibration and never corrects homographies: its tracker keeps the map.
    lens_hook = calibrator.get("estimate_distortion") is True and calibrator.get("focal_model") != "constant"
    if calibrator.get("state_dir") and not lens_hook and "state_dir" not in tracker:
        tracker["state_dir"] = calibrator["state_dir"]
    return [NodeLaunch(name, modules[name], ns, params[name], pairs) for name in nodes]


def state_root(environ: dict[str, str] | None = None) -> str:
    """Where `launch` keeps each camera's state by default: $ROS_HOME/ptz_selfcal (ROS_HOME defaults to
    ~/.ros, as for ROS's own logs and camera_info_manager's files)."""
    environ = os.environ if environ is None else environ
    home = environ.get("ROS_HOME") or str(Path(environ.get("HOME") or Path.home()) / ".ros")
    return str(Path(home) / "ptz_selfcal")


def plan_params_file(plan: Sequence[NodeLaunch], directory: str) -> Path:
    """The plan's parameters as one parameter file, a section per node under its fully qualified name."""
    import yaml

    out = {n.fully_qualified_name: {"ros__parameters": dict(n.parameters)} for n in plan}
    path = Path(directory) / "params.yaml"
    path.write_text(yaml.safe_dump(out, sort_keys=False))
    return path


def check_remaps(remaps: Sequence[str]) -> list[str]:
    for remap in remaps:
        src, sep, dst = remap.partition(":=")
        if not sep or not src or not dst:
            raise CliError(f"--remap wants FROM:=TO, got {remap!r}")
    return list(remaps)


def check_namespace(namespace: str | None) -> str | None:
    if not namespace:
        return None
    ns = namespace if namespace.startswith("/") else "/" + namespace
    parts = ns.strip("/").split("/")
    if not all(p and (p[0].isalpha() or p[0] == "_") and p.replace("_", "").isalnum() for p in parts):
        raise CliError(f"--namespace {namespace!r} is not a valid ROS namespace")
    return ns.rstrip("/")


# ---------------------------------------------------------------------------------------------------------
# the supervisor


@dataclass
class NodeSpec:
    name: str
    module: str
    args: list[str] = field(default_factory=list)  # extra --ros-args arguments (after the params file)


@dataclass
class _Child:
    spec: NodeSpec
    process: subprocess.Popen | None = None
    started: float = 0.0
    starts: int = 0
    restarts: int = 0
    failures: int = 0  # consecutive quick deaths (backoff exponent)
    restart_at: float | None = None
    tail: deque[str] = field(default_factory=lambda: deque(maxlen=20))
    reader: threading.Thread | None = None


def _libc_prctl() -> Any:
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # not Linux/glibc: children are still stopped by stop()
        return None


# Resolved once in the parent: the child (between fork and exec, possibly with other threads in the
# parent) only makes the call, it loads nothing.
_PRCTL = _libc_prctl()


def _set_pdeathsig() -> None:  # runs in the child between fork and exec
    if _PRCTL is not None:
        _PRCTL(1, signal.SIGTERM)  # PR_SET_PDEATHSIG: SIGTERM when the supervisor dies


class SupervisorError(Exception):
    """The suite cannot run (a node failed at start-up or has a configuration error)."""


class Supervisor:
    """Starts node processes, prefixes their output, restarts them, stops them cleanly."""

    def __init__(
        self,
        specs: Sequence[NodeSpec],
        params_file: str | os.PathLike[str] | None = None,
        namespace: str | None = None,
        remaps: Sequence[str] = (),
        output: IO[str] | None = None,
        startup_grace: float = 3.0,
        stable_after: float = 30.0,
        max_backoff: float = 30.0,
        echo: bool = True,
        log: Callable[[str], None] | None = None,
        nice: int | None = None,
        env: dict[str, str] | None = None,
    ) -> None:
        self.children = [_Child(spec) for spec in specs]
        self.nice = nice
        self.env = dict(env or {})  # added to the supervisor's environment for the nodes
        self.params_file = str(params_file) if params_file else None
        self.namespace = namespace
        self.remaps = list(remaps)
        self.output = output or sys.stdout
        self.echo = echo
        self.startup_grace = startup_grace
        self.stable_after = stable_after
        self.max_backoff = max_backoff
        self._lock = threading.Lock()
        self._stopping = False
        self.fatal: str | None = None
        self.final_cpu_seconds: dict[str, float] = {}
        self.log = log or (lambda text: self._write(f"[launch] {text}\n"))

    # -- output
    def _write(self, text: str) -> None:
        with self._lock:
            try:
                self.output.write(text)
                self.output.flush()
            except (OSError, ValueError):
                pass

    def _pump(self, child: _Child, stream: IO[bytes]) -> None:
        for raw in iter(stream.readline, b""):
            line = raw.decode(errors="replace").rstrip("\n")
            child.tail.append(line)
            if self.echo:
                self._write(f"[{child.spec.name}] {line}\n")
        stream.close()

    # -- processes
    def command(self, spec: NodeSpec) -> list[str]:
        cmd = [sys.executable, "-m", spec.module, "--ros-args", "-r", f"__node:={spec.name}"]
        if self.namespace:
            cmd += ["-r", f"__ns:={self.namespace}"]
        if self.params_file:
            cmd += ["--params-file", self.params_file]
        for remap in self.remaps:
            cmd += ["-r", remap]
        return cmd + list(spec.args)

    def _spawn(self, child: _Child) -> None:
        env = {**os.environ, **self.env}
        env.setdefault("PYTHONUNBUFFERED", "1")
        env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
        child.process = subprocess.Popen(
            self.command(child.spec),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,  # Ctrl-C reaches the supervisor only; it stops the children in order
            preexec_fn=_set_pdeathsig,
        )
        if self.nice is not None:
            self._prioritise(child.process.pid)
        child.started = time.monotonic()
        child.starts += 1
        child.restart_at = None
        child.reader = threading.Thread(target=self._pump, args=(child, child.process.stdout), daemon=True)
        child.reader.start()
        self.log(f"started {child.spec.name} (pid {child.process.pid})")

    def _prioritise(self, pid: int) -> None:
        """Niceness of a just-started node: of its session's autogroup (with the kernel's autogroups every
        session shares the CPU equally, and each node has its own session) and of its main thread (the
        threads it starts inherit it). Measured (benchmarks/live_latency.py, load 11-13 on 2 CPUs): -10
        brought the live 30 fps p95 latency from 84-558 ms (4 runs) to 37-49 ms in 5 of 6 runs (136 ms in
        one)."""
        with contextlib.suppress(OSError):  # no autogroups on this kernel: the thread nice still applies
            Path(f"/proc/{pid}/autogroup").write_text(str(self.nice))
        try:
            os.setpriority(os.PRIO_PROCESS, pid, self.nice)
        except OSError as exc:
            self.log(f"cannot set nice {self.nice} for pid {pid}: {exc.strerror or exc}")

    def start(self) -> None:
        for child in self.children:
            self._spawn(child)

    def pids(self) -> dict[str, int]:
        return {c.spec.name: c.process.pid for c in self.children if c.process is not None}

    @property
    def restarts(self) -> dict[str, int]:
        return {c.spec.name: c.restarts for c in self.children}

    def poll(self) -> None:
        """Notice dead children and restart them (with backoff); sets `fatal` when the suite cannot run."""
        now = time.monotonic()
        for child in self.children:
            if self._stopping or self.fatal:
                return
            proc = child.process
            if proc is None:
                if child.restart_at is not None and now >= child.restart_at:
                    child.restarts += 1
                    self._spawn(child)
                continue
            code = proc.poll()
            if code is None:
                if now - child.started > self.stable_after:
                    child.failures = 0
                continue
            if child.reader is not None:
                child.reader.join(timeout=1.0)
            lived = now - child.started
            child.process = None
            last = next((line for line in reversed(child.tail) if line.strip()), "")
            # Its configuration error, or an error exit (not a signal) right after the first start (e.g. the
            # module cannot be imported): restarting cannot help. Anything else is restarted.
            if code == CONFIG_ERROR_STATUS or (code > 0 and child.starts == 1 and lived < self.startup_grace):
                self.fatal = f"{child.spec.name} exited with status {code} at start-up" + (
                    f": {last}" if last else ""
                )
                self.log(self.fatal)
                return
            child.failures = child.failures + 1 if lived < self.stable_after else 1
            delay = min(self.max_backoff, 0.5 * 2 ** (child.failures - 1))
            child.restart_at = now + delay
            self.log(
                f"{child.spec.name} exited unexpectedly with status {code} after {lived:.1f} s; "
                f"restart #{child.restarts + 1} in {delay:.1f} s"
            )

    def running(self) -> list[str]:
        return [c.spec.name for c in self.children if c.process is not None and c.process.poll() is None]

    def cpu_seconds(self) -> dict[str, float]:
        """CPU time (user + system) used so far by each running child (Linux /proc)."""
        out = {}
        for c in self.children:
            if c.process is None:
                continue
            try:
                fields = Path(f"/proc/{c.process.pid}/stat").read_text().rsplit(")", 1)[1].split()
                out[c.spec.name] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            except (OSError, ValueError, IndexError):
                pass
        return out

    def stop(self, timeout: float = 5.0, term_timeout: float = 3.0) -> dict[str, int | None]:
        """SIGINT every child, wait up to `timeout`, then SIGTERM, then SIGKILL. Returns exit codes."""
        self._stopping = True
        self.final_cpu_seconds = self.cpu_seconds()
        procs = {c.spec.name: c.process for c in self.children if c.process is not None}
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, term_timeout), (signal.SIGKILL, 5.0)):
            alive = {n: p for n, p in procs.items() if p.poll() is None}
            if not alive:
                break
            if sig != signal.SIGINT:
                self.log(f"{', '.join(alive)} still running: sending {signal.Signals(sig).name}")
            for proc in alive.values():
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(sig)
            deadline = time.monotonic() + wait
            for proc in alive.values():
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        codes = {n: p.poll() for n, p in procs.items()}
        for child in self.children:
            if child.reader is not None:
                child.reader.join(timeout=1.0)
        return codes


# ---------------------------------------------------------------------------------------------------------
# command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--params", metavar="FILE", help="parameter YAML (default: config/ptz_selfcal.yaml)")
    parser.add_argument(
        "--namespace", metavar="NS", help="the camera's namespace, where its image_raw is (default /ptz)"
    )
    parser.add_argument(
        "--camera-name",
        metavar="NAME",
        help="camera_name of every node, the diagnostics' hardware_id (default: the parameter file's, "
        "else the namespace's last component)",
    )
    parser.add_argument(
        "--remap", nargs="+", default=[], metavar="FROM:=TO", help="topic remappings given to every node"
    )
    parser.add_argument(
        "--no-persist",
        action="store_true",
        help="no calibration state unless the parameter file sets a state_dir (default: the calibrator "
        "without one keeps its state in $ROS_HOME/ptz_selfcal/<camera_name>)",
    )
    parser.add_argument(
        "--nodes",
        nargs="+",
        choices=list(NODE_MODULES),
        default=list(SUITE_NODES),
        help="start only these nodes (default: the suite's three; mosaic is the optional live mosaic)",
    )
    parser.add_argument(
        "--mosaic",
        action="store_true",
        help="also start the live mosaic node (selfcal/mosaic: CONVERGED frames on a spherical canvas)",
    )
    parser.add_argument("--stop-timeout", type=float, default=5.0, help="seconds to wait after SIGINT")
    parser.add_argument(
        "--nice",
        type=int,
        metavar="N",
        help="run the nodes at niceness N (-20..19; negative needs CAP_SYS_NICE), e.g. -10 to keep a live "
        "camera's latency low on a machine busy with other work",
    )
    parser.add_argument(
        "--dds-lease",
        type=float,
        metavar="SECONDS",
        help="Fast DDS participant lease of the nodes: a killed node's endpoints leave the graph after this "
        "long; 0 keeps the middleware's (20 s) (default: config/fastdds.xml's, 2 s)",
    )
    # Tests (and experiments) may replace a node's module: --node-module calibrator=my_package.my_node
    parser.add_argument(
        "--node-module", action="append", default=[], metavar="NAME=MODULE", help=argparse.SUPPRESS
    )


def profile_named(environ: dict[str, str] | None = None) -> str | None:
    """The Fast DDS profile file the environment names, if any."""
    environ = os.environ if environ is None else environ
    return next((environ[v] for v in PROFILE_VARIABLES if environ.get(v)), None)


def dds_profile_environment(
    directory: str | None = None, lease: float | None = None, environ: dict[str, str] | None = None
) -> dict[str, str]:
    """Environment variables that give a process's Fast DDS participants the shipped profile
    (config/fastdds.xml); with `lease` (seconds, announced every lease / 4; 0: the middleware's) a copy
    of it with that participant lease, written into `directory`. Empty when the middleware is not Fast
    DDS, when the environment names a profile file other than the shipped one (the user's
    configuration wins) or when the package was installed without it.

    Static peers (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST with ROS_STATIC_PEERS, a suite across hosts):
    with a directory, the copy also carries the peers as its discovery (profile_with_static_peers) and
    the range becomes SYSTEM_DEFAULT for the process. Under LOCALHOST, Jazzy's rmw_fastrtps adds its own
    shared-memory and UDPv4 transports to the profile's, and every datagram to another host is sent by
    both UDPv4 transports; under SYSTEM_DEFAULT it leaves the profile's alone."""
    environ = os.environ if environ is None else environ
    rmw = environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    shipped = default_profile_file()
    named = profile_named(environ)
    if not rmw.startswith("rmw_fastrtps") or (named and Path(named).resolve() != shipped.resolve()):
        return {}
    if not shipped.is_file():  # Fast DDS would only log that it cannot read the file named
        return {}
    peers = static_peers(environ) if directory is not None else []
    if lease is None and not peers:
        return {PROFILE_VARIABLES[0]: str(shipped)}
    if directory is None:
        raise ValueError("a profile with another lease needs a directory to be written into")
    text, name, env = shipped.read_text(), "fastdds", {}
    if lease is not None:
        text, name = profile_with_lease(text, lease), f"{name}_lease_{lease:g}"
    if peers:
        text, name = profile_with_static_peers(text, peers), f"{name}_static_peers"
        env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT", "ROS_STATIC_PEERS": ""}
    path = Path(directory) / f"{name}.xml"
    path.write_text(text)
    return {PROFILE_VARIABLES[0]: str(path), **env}


def static_peers(environ: dict[str, str]) -> list[str]:
    """The IPv4 addresses of ROS_STATIC_PEERS (names resolved, as rmw_fastrtps takes a name's first IPv4
    address) when discovery is LOCALHOST with static peers; [] otherwise."""
    import socket

    if environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") != "LOCALHOST":
        return []
    peers = []
    for peer in (p.strip() for p in environ.get("ROS_STATIC_PEERS", "").split(";")):
        if peer:
            try:
                peers.append(socket.gethostbyname(peer))
            except OSError as exc:
                raise CliError(f"ROS_STATIC_PEERS: cannot resolve {peer!r} ({exc})") from exc
    return peers


def profile_with_static_peers(text: str, peers: Sequence[str]) -> str:
    """A Fast DDS profile's text whose default participant discovers what rmw_fastrtps's LOCALHOST range
    with static peers discovers: unicast announcements to 127.0.0.1 and to `peers` (IPv4 addresses), the
    first 32 participants of each, as rmw_fastrtps's own UDPv4 transport has it; a unicast metatraffic
    locator, so that no multicast one is created and nothing is multicast."""
    import xml.etree.ElementTree as ET

    namespace = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"
    ET.register_namespace("", namespace)
    root = ET.fromstring(text)

    def tag(name: str) -> str:
        return f"{{{namespace}}}{name}"

    def child(parent: ET.Element, name: str) -> ET.Element:
        found = parent.find(tag(name))
        return found if found is not None else ET.SubElement(parent, tag(name))

    participant = next(p for p in root.iter(tag("participant")) if p.get("is_default_profile") == "true")
    builtin = child(child(participant, "rtps"), "builtin")
    for name in ("metatrafficUnicastLocatorList", "initialPeersList"):
        old = builtin.find(tag(name))
        if old is not None:
            builtin.remove(old)
    unicast = ET.SubElement(builtin, tag("metatrafficUnicastLocatorList"))
    ET.SubElement(ET.SubElement(unicast, tag("locator")), tag("udpv4"))
    initial = ET.SubElement(builtin, tag("initialPeersList"))
    for address in dict.fromkeys(["127.0.0.1", *peers]):
        udp = ET.SubElement(ET.SubElement(initial, tag("locator")), tag("udpv4"))
        ET.SubElement(udp, tag("address")).text = address
    for descriptor in root.iter(tag("transport_descriptor")):
        if descriptor.findtext(tag("type")) == "UDPv4":
            child(descriptor, "maxInitialPeersRange").text = "32"
    return '<?xml version="1.0" encoding="UTF-8" ?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def profile_with_lease(text: str, lease: float) -> str:
    """A Fast DDS profile's text with its default participant's lease set to `lease` seconds (announced
    every lease / 4), or with no lease of its own when lease is 0 (the middleware's default)."""
    import xml.etree.ElementTree as ET

    namespace = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"
    ET.register_namespace("", namespace)  # Fast DDS's parser reads plain tag names, no prefixes
    root = ET.fromstring(text)

    def child(parent: ET.Element, tag: str) -> ET.Element:
        found = parent.find(f"{{{namespace}}}{tag}")
        return found if found is not None else ET.SubElement(parent, f"{{{namespace}}}{tag}")

    participant = next(
        p for p in root.iter(f"{{{namespace}}}participant") if p.get("is_default_profile") == "true"
    )
    config = child(child(child(participant, "rtps"), "builtin"), "discovery_config")
    for tag, seconds in (("leaseDuration", lease), ("leaseAnnouncement", lease / 4)):
        old = config.find(f"{{{namespace}}}{tag}")
        if old is not None:
            config.remove(old)
        if lease > 0:
            ns = round(seconds * 1e9)
            node = ET.SubElement(config, f"{{{namespace}}}{tag}")
            ET.SubElement(node, f"{{{namespace}}}sec").text = str(ns // 1_000_000_000)
            ET.SubElement(node, f"{{{namespace}}}nanosec").text = str(ns % 1_000_000_000)
    return '<?xml version="1.0" encoding="UTF-8" ?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def prepare(
    params: str | None, namespace: str | None, remaps: Sequence[str], tmpdir: str
) -> tuple[Path, str, list[str]]:
    """Validate the command-line inputs of a suite in a namespace of the caller's (run, benchmarks):
    the params file to pass to the nodes (plan_suite's), the namespace and the remaps."""
    source = Path(params) if params else default_params_file()
    data = load_params_file(source, list(NODE_MODULES))
    plan = plan_suite(data, namespace, remaps, name_from_namespace=False)
    return plan_params_file(plan, tmpdir), plan[0].namespace, check_remaps(remaps)


def run(args: argparse.Namespace) -> int:
    if not args.stop_timeout > 0:
        raise CliError("--stop-timeout must be > 0")
    if args.nice is not None and not -20 <= args.nice <= 19:
        raise CliError(f"--nice must be in [-20, 19], got {args.nice}")
    if args.dds_lease is not None and not (args.dds_lease == 0 or 0.5 <= args.dds_lease <= 3600):
        raise CliError(f"--dds-lease must be 0 or in [0.5, 3600] s, got {args.dds_lease}")
    with tempfile.TemporaryDirectory(prefix="ptz_selfcal_launch_") as tmp:
        modules = dict(NODE_MODULES)
        for item in args.node_module:
            name, sep, module = item.partition("=")
            if not sep or name not in modules or not module:
                raise CliError(
                    f"--node-module wants NAME=MODULE with NAME in {', '.join(modules)}, got {item!r}"
                )
            modules[name] = module
        source = Path(args.params) if args.params else default_params_file()
        data = load_params_file(source, list(NODE_MODULES))
        root = None if args.no_persist else state_root()
        nodes = list(args.nodes) + (["mosaic"] if args.mosaic and "mosaic" not in args.nodes else [])
        plan = plan_suite(data, args.namespace, args.remap, args.camera_name, nodes, modules, state_root=root)
        specs = [NodeSpec(n.name, n.module) for n in plan]
        remaps = [f"{src}:={dst}" for src, dst in plan[0].remappings] if plan else []
        namespace = plan[0].namespace if plan else None
        env = dds_profile_environment(tmp, args.dds_lease)
        supervisor = Supervisor(
            specs, plan_params_file(plan, tmp), namespace, remaps, nice=args.nice, env=env
        )
        if env:
            peers = (
                " (static peers in it: ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT)"
                if "ROS_STATIC_PEERS" in env
                else ""
            )
            supervisor.log(f"Fast DDS profile {env[PROFILE_VARIABLES[0]]}{peers}")
        elif profile_named():
            supervisor.log(
                f"Fast DDS profile of the environment: {profile_named()} (ptz_selfcal's, "
                f"{default_profile_file()}, is not loaded: its shared-memory segment and participant lease "
                "apply only if yours has them)"
            )
        stop = threading.Event()

        def on_signal(signum: int, _frame: Any) -> None:
            stop.set()

        previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            supervisor.start()
            while not stop.is_set() and supervisor.fatal is None:
                supervisor.poll()
                stop.wait(0.1)
        finally:
            supervisor.log("stopping")
            codes = supervisor.stop(timeout=args.stop_timeout)
            for s, handler in previous.items():
                signal.signal(s, handler)
            summary = ", ".join(f"{n}: {c}" for n, c in codes.items())
            restarts = sum(supervisor.restarts.values())
            supervisor.log(f"stopped ({summary}); {restarts} restarts")
        if supervisor.fatal is not None:
            raise CliError(supervisor.fatal)
    return 0
