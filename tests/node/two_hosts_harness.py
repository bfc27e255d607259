"""Two simulated hosts on this machine: two network namespaces of their own joined by a veth pair, for
the cross-host test (test_two_hosts.py) and benchmark (benchmarks/two_hosts.py).

Each namespace has only its loopback and its end of the link (a private /30, IPv6 off so the kernel
sends no multicast of its own on it): nothing in them reaches another machine. The nodes discover each
other through static peers only: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST with ROS_STATIC_PEERS naming
both hosts' addresses (one site-wide list, as every box of a deployment would have it). Jazzy's
rmw_fastrtps then sends discovery by unicast to 127.0.0.1 and to the peers and listens to no multicast
(launch gives its nodes the same discovery in a copy of the shipped profile: dds_profile_environment);
OFF would ignore the peers and allow no remote participant at all.

Shared memory: both namespaces see the same /dev/shm, but Fast DDS uses a peer's shared-memory
locators only when the peer has its own host id, a hash of the IPv4 addresses of the interfaces; the
namespaces' addresses differ as two machines' do, so what goes between them goes over UDP (the
link's byte counters, and the segments each process maps, show it).

Not a conftest.py: test modules and the benchmark import it by name.
"""

from __future__ import annotations

import ctypes
import json
import os
import re
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ptz_selfcal.tools.launch import NodeSpec, Supervisor

CLONE_NEWNET = 0x40000000
_SEGMENT = re.compile(r"/dev/shm/(fastrtps_[0-9a-f]{16})$")


@dataclass(frozen=True)
class Host:
    netns: str
    interface: str
    address: str


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


class TwoHosts:
    """Namespaces "camera" (a) and "server" (b), names unique to this process; close() removes them."""

    def __init__(self, tag: str | None = None, subnet: str = "10.231.0") -> None:
        tag = tag or f"ptz{os.getpid()}"
        self.a = Host(f"{tag}a", f"{tag}a"[-15:], f"{subnet}.1")  # interface names: 15 characters at most
        self.b = Host(f"{tag}b", f"{tag}b"[-15:], f"{subnet}.2")
        self._created: list[str] = []
        try:
            self._create()
        except BaseException:
            self.close()
            raise

    def _run(self, *args: str) -> None:
        result = _ip(*args)
        if result.returncode != 0:
            raise OSError(f"ip {' '.join(args)}: {result.stderr.strip() or result.returncode}")

    def _create(self) -> None:
        for host in (self.a, self.b):
            self._run("netns", "add", host.netns)
            self._created.append(host.netns)
        a, b = self.a, self.b
        self._run("link", "add", a.interface, "netns", a.netns, "type", "veth", "peer", "name", b.interface,
                  "netns", b.netns)  # fmt: skip
        for host in (a, b):
            self._run("-n", host.netns, "link", "set", "lo", "up")
            path = f"/proc/sys/net/ipv6/conf/{host.interface}/disable_ipv6"
            self._run("netns", "exec", host.netns, "sh", "-c", f"echo 1 > {path}")
            self._run("-n", host.netns, "addr", "add", f"{host.address}/30", "dev", host.interface)
            self._run("-n", host.netns, "link", "set", host.interface, "up")
        # A participant takes the addresses of the interfaces that are running when it starts: one
        # started before the link has its carrier (a moment after "up") announces no address on it.
        deadline = time.monotonic() + 10.0
        while not all(self._operstate(h) == "UP" for h in (a, b)):
            if time.monotonic() > deadline:
                raise OSError(f"the veth pair has no carrier: {[self._operstate(h) for h in (a, b)]}")
            time.sleep(0.02)

    def _operstate(self, host: Host) -> str:
        result = _ip("-n", host.netns, "-j", "link", "show", "dev", host.interface)
        return json.loads(result.stdout)[0].get("operstate", "") if result.returncode == 0 else ""

    def close(self) -> None:
        """Remove the namespaces (the veth pair goes with them once their last process has left)."""
        while self._created:
            _ip("netns", "del", self._created.pop())

    def __enter__(self) -> TwoHosts:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def static_peers(self) -> str:
        return f"{self.a.address};{self.b.address}"

    def environment(self) -> dict[str, str]:
        """What every process of the two hosts adds to its environment: static-peer discovery."""
        return {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_STATIC_PEERS": self.static_peers}

    def counters(self, host: Host) -> dict[str, int]:
        """The link end's byte, packet and multicast counters (rx_bytes, tx_bytes, rx_multicast, ...)."""
        result = _ip("-n", host.netns, "-j", "-s", "link", "show", "dev", host.interface)
        if result.returncode != 0:
            raise OSError(result.stderr.strip())
        stats = json.loads(result.stdout)[0]["stats64"]
        return {f"{d}_{k}": int(v) for d in ("rx", "tx") for k, v in stats[d].items()}

    def udp_receive_errors(self, host: Host) -> int:
        """Datagrams the host's kernel dropped for a full socket receive buffer (Udp RcvbufErrors)."""
        result = subprocess.run(["ip", "netns", "exec", host.netns, "cat", "/proc/net/snmp"],
                                capture_output=True, text=True, timeout=10)  # fmt: skip
        names, values = [line.split()[1:] for line in result.stdout.splitlines() if line.startswith("Udp:")][
            :2
        ]
        return int(dict(zip(names, values, strict=True))["RcvbufErrors"])


def in_netns(netns: str, cmd: Sequence[str]) -> list[str]:
    """`cmd` run in a namespace (`ip netns exec` switches and execs: the process keeps its pid)."""
    return ["ip", "netns", "exec", netns, *cmd]


def enter(netns: str) -> None:
    """Move the calling thread, and the threads it starts from now on, into a namespace (as `ip netns
    exec` does before it execs): call before the process's first DDS participant."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.open(f"/run/netns/{netns}", os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            raise OSError(ctypes.get_errno(), f"setns {netns}")
    finally:
        os.close(fd)


def unavailable() -> str | None:
    """Why network namespaces cannot be created here, or None when they can."""
    probe = f"ptzprobe{os.getpid()}"
    try:
        result = _ip("netns", "add", probe)
    except OSError as exc:  # no `ip` (iproute2) on this machine
        return f"cannot create a network namespace ({exc})"
    if result.returncode != 0:
        return f"cannot create a network namespace (ip netns add: {result.stderr.strip()})"
    _ip("netns", "del", probe)
    return None


def shm_segments(pid: int) -> set[str]:
    """The Fast DDS shared-memory segments a process has mapped: its own and those of every peer it
    reads from by shared memory."""
    try:
        lines = Path(f"/proc/{pid}/maps").read_text().splitlines()
    except OSError:
        return set()
    return {m.group(1) for m in map(_SEGMENT.search, lines) if m}


class NetnsSupervisor(Supervisor):
    """launch's Supervisor with some nodes started in another network namespace."""

    def __init__(self, *args, netns: dict[str, str], **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.netns = netns  # node name -> namespace; the others run in the supervisor's

    def command(self, spec: NodeSpec) -> list[str]:
        cmd = super().command(spec)
        return in_netns(self.netns[spec.name], cmd) if spec.name in self.netns else cmd
