"""The one Fast DDS profile (config/fastdds.xml) that launch, run, the launch file and the tests give the
nodes: what it sets, and who gets which file."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from ptz_selfcal.tools.launch import (
    PROFILE_VARIABLES,
    dds_profile_environment,
    default_profile_file,
    profile_with_lease,
)

NS = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
FAST_DDS = {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}


def _participant(path: Path) -> ET.Element:
    (participant,) = [
        p
        for p in ET.parse(path).getroot().findall("f:participant", NS)
        if p.get("is_default_profile") == "true"
    ]
    return participant


def _lease(path: Path) -> tuple[float, float] | None:
    config = _participant(path).find("f:rtps/f:builtin/f:discovery_config", NS)

    def seconds(tag: str) -> float | None:
        node = config.find(f"f:{tag}", NS)
        return (
            None
            if node is None
            else int(node.find("f:sec", NS).text) + 1e-9 * int(node.find("f:nanosec", NS).text)
        )

    duration, announce = seconds("leaseDuration"), seconds("leaseAnnouncement")
    return None if duration is None else (duration, announce)


def test_the_shipped_profile_carries_raw_images_in_shared_memory_and_a_short_lease():
    """A shared-memory segment that holds several raw 1920x1080 colour images (the default 512 KB does not
    hold one 1280x720 image), UDPv4 beside it (discovery, other hosts) instead of the built-in pair, with
    a receive buffer for frames from another host, and the 2 s lease launch has always given the nodes."""
    path = default_profile_file()
    assert path.name == "fastdds.xml" and path.parent.name == "config"
    root = ET.parse(path).getroot()
    descriptors = {
        d.find("f:transport_id", NS).text: d
        for d in root.findall("f:transport_descriptors/f:transport_descriptor", NS)
    }
    participant = _participant(path)
    used = [t.text for t in participant.findall("f:rtps/f:userTransports/f:transport_id", NS)]
    kinds = {descriptors[t].find("f:type", NS).text: descriptors[t] for t in used}
    assert set(kinds) == {"SHM", "UDPv4"}
    assert participant.find("f:rtps/f:useBuiltinTransports", NS).text == "false"
    assert int(kinds["SHM"].find("f:segment_size", NS).text) >= 4 * 1920 * 1080 * 3
    # frames from another host: a burst of working-resolution frames (640x360 mono8) fits the socket's
    # buffer with the kernel's overhead per fragment (the system default drops, and the drops are re-sent)
    assert int(kinds["UDPv4"].find("f:receiveBufferSize", NS).text) >= 8 * 640 * 360 * 2
    assert _lease(path) == (2.0, 0.5)


def test_every_process_gets_the_shipped_profile_unless_the_user_names_another(tmp_path):
    shipped = str(default_profile_file())
    assert dds_profile_environment(environ=FAST_DDS) == {PROFILE_VARIABLES[0]: shipped}
    assert dds_profile_environment(environ={}) == {PROFILE_VARIABLES[0]: shipped}  # Fast DDS is the default
    # the environment naming the shipped file already (the tests' ros_env) is no user's profile
    assert dds_profile_environment(environ={PROFILE_VARIABLES[0]: shipped}) == {PROFILE_VARIABLES[0]: shipped}
    for environ in ({PROFILE_VARIABLES[0]: "/etc/mine.xml"}, {PROFILE_VARIABLES[1]: "/etc/mine.xml"},
                    {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}):  # fmt: skip
        assert dds_profile_environment(str(tmp_path), 2.0, environ) == {}, environ
    assert list(tmp_path.iterdir()) == []


def test_another_lease_is_a_copy_of_the_shipped_profile(tmp_path):
    """launch --dds-lease: the same transports with that lease (announced every lease / 4); 0 leaves the
    lease to the middleware."""
    ((variable, path),) = dds_profile_environment(str(tmp_path), 2.5, FAST_DDS).items()
    assert variable == PROFILE_VARIABLES[0] and Path(path).parent == tmp_path
    assert _lease(Path(path)) == (2.5, 0.625)
    shipped = ET.tostring(_participant(default_profile_file()).find("f:rtps/f:userTransports", NS))
    assert ET.tostring(_participant(Path(path)).find("f:rtps/f:userTransports", NS)) == shipped
    ((_, none),) = dds_profile_environment(str(tmp_path), 0.0, FAST_DDS).items()
    assert _lease(Path(none)) is None
    # plain tag names: Fast DDS's parser does not resolve namespace prefixes
    assert "ns0:" not in profile_with_lease(default_profile_file().read_text(), 3.0)


def test_no_profile_named_when_the_package_has_none(monkeypatch, tmp_path):
    """An install without config/fastdds.xml names no file (Fast DDS would only log that it is missing)."""
    from ptz_selfcal.tools import launch

    monkeypatch.setattr(launch, "default_profile_file", lambda: tmp_path / "fastdds.xml")
    assert launch.dds_profile_environment(str(tmp_path), None, FAST_DDS) == {}


def test_static_peers_become_the_profile_s_unicast_discovery(tmp_path):
    """LOCALHOST with ROS_STATIC_PEERS (a suite across hosts): a copy of the shipped profile whose
    discovery is unicast to 127.0.0.1 and the peers (32 participants each, as rmw_fastrtps's LOCALHOST
    transport), no multicast locator, and the range SYSTEM_DEFAULT so that rmw_fastrtps adds no second
    UDPv4 transport; the transports and the lease stay the shipped ones."""
    environ = {
        **FAST_DDS,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_STATIC_PEERS": "10.0.0.2; localhost;",
    }
    env = dds_profile_environment(str(tmp_path), None, environ)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT" and env["ROS_STATIC_PEERS"] == ""
    path = Path(env[PROFILE_VARIABLES[0]])
    builtin = _participant(path).find("f:rtps/f:builtin", NS)
    peers = [a.text for a in builtin.findall("f:initialPeersList/f:locator/f:udpv4/f:address", NS)]
    assert peers == ["127.0.0.1", "10.0.0.2"]  # localhost once
    (unicast,) = builtin.findall("f:metatrafficUnicastLocatorList/f:locator", NS)
    assert (
        unicast.find("f:udpv4", NS) is not None
        and builtin.find("f:metatrafficMulticastLocatorList", NS) is None
    )
    udp = [d for d in ET.parse(path).getroot().iter(f"{{{NS['f']}}}transport_descriptor")
           if d.find("f:type", NS).text == "UDPv4"]  # fmt: skip
    assert [d.find("f:maxInitialPeersRange", NS).text for d in udp] == ["32"]
    shipped = ET.tostring(_participant(default_profile_file()).find("f:rtps/f:userTransports", NS))
    assert ET.tostring(_participant(path).find("f:rtps/f:userTransports", NS)) == shipped
    assert _lease(path) == (2.0, 0.5)
    leased = dds_profile_environment(str(tmp_path), 3.0, environ)
    assert _lease(Path(leased[PROFILE_VARIABLES[0]])) == (3.0, 0.75)
    # no peers, another range, or nowhere to write: the shipped file as it is
    for other in (
        {**environ, "ROS_STATIC_PEERS": ""},
        {**environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"},
    ):
        assert dds_profile_environment(str(tmp_path), None, other) == {
            PROFILE_VARIABLES[0]: str(default_profile_file())
        }
    assert dds_profile_environment(None, None, environ) == {PROFILE_VARIABLES[0]: str(default_profile_file())}
