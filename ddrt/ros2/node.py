"""A ROS 2 node on bare DDS: the participant, its topics with ROS 2's QoS, and the
discovery information that makes `ros2 node list` and `ros2 topic info -v` show it.

What ROS 2 expects of a peer on the wire (rmw_dds_common and the rmw implementations):
- topic names `rt/<namespace>/<name>`, type names `<pkg>::msg::dds_::<Type>_`;
- each endpoint's USER_DATA `typehash=RIHS01_<hex>;` (ddrt/ros2/typehash.py), the
  participant's `enclave=/;`;
- the participant publishes `ros_discovery_info` (rmw_dds_common/msg/ParticipantEntitiesInfo:
  its GUID and, per node, its name, namespace and the GUIDs of its readers and writers),
  reliable and transient-local, so a late `ros2 node list` still sees it. Without it a
  participant shows as `_CREATED_BY_BARE_DDS_APP_`.

Fast DDS 3 (ROS 2 Kilted's default middleware) sends XTypes type information whose array and
sequence elements have both "try construct" bits 0; Cyclone DDS 11 rejects those type objects
as invalid (and, told to accept them, finds them not assignable to its own), so no message type
with an array or a sequence would match. The bridge's domain therefore ignores the type
information of eProsima's participants (vendor id 1.15) and matches them on the type name, as
it does Fast DDS 2 (Jazzy) and rmw_cyclonedds peers, which send none. docs/ros2.md has the
measurements.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from cyclonedds.core import DDSException
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from ddrt.ros2.idl import msg
from ddrt.ros2.typehash import user_data

DISCOVERY_TOPIC = "ros_discovery_info"
DISCOVERY_TYPE = "rmw_dds_common/msg/ParticipantEntitiesInfo"


@dataclass(frozen=True)
class QosProfile:
    """The few ROS 2 QoS settings the bridge uses (rclcpp's names)."""

    depth: int = 10
    reliable: bool = True
    transient_local: bool = False


DEFAULT = QosProfile()  # rclcpp's default, and diff_drive_controller's odometry and cmd_vel
TF = QosProfile(depth=100)  # tf2_ros.TransformBroadcaster
TF_STATIC = QosProfile(depth=1, transient_local=True)  # tf2_ros.StaticTransformBroadcaster
DISCOVERY = QosProfile(depth=1, transient_local=True)

EPROSIMA_VENDOR_ID = "1.15"  # Fast DDS
DOMAIN_XML = ("<CycloneDDS><Domain><Compatibility><IgnoreTypeInformation>" + EPROSIMA_VENDOR_ID
              + "</IgnoreTypeInformation></Compatibility></Domain></CycloneDDS>")
_DOMAINS: dict[int, Any] = {}


def domain_config(user_uri: str) -> str:
    """The bridge's Cyclone DDS configuration: DOMAIN_XML, amended by the user's CYCLONEDDS_URI
    (files and XML fragments, applied after ours, so a user's setting wins)."""
    return DOMAIN_XML + ("," + user_uri if user_uri.strip() else "")


def participant(domain_id: int, qos: Qos) -> DomainParticipant:
    """A participant in `domain_id`, whose domain is created with domain_config on first use."""
    if domain_id not in _DOMAINS:
        try:
            _DOMAINS[domain_id] = Domain(domain_id, domain_config(os.environ.get("CYCLONEDDS_URI", "")))
        except DDSException as exc:
            if exc.code != DDSException.DDS_RETCODE_PRECONDITION_NOT_MET:
                raise
            _DOMAINS[domain_id] = None  # created before in this process (not by us): its config stands
    return DomainParticipant(domain_id, qos=qos)


def dds_qos(profile: QosProfile, type_name: str | None) -> Qos:
    policies: list[Any] = [
        Policy.History.KeepLast(profile.depth),
        Policy.Reliability.Reliable(duration(milliseconds=100)) if profile.reliable
        else Policy.Reliability.BestEffort,
        Policy.Durability.TransientLocal if profile.transient_local else Policy.Durability.Volatile,
        Policy.DataRepresentation(use_cdrv0_representation=True),
    ]
    if type_name is not None:
        policies.append(Policy.Userdata(user_data(type_name)))
    return Qos(*policies)


def topic_name(namespace: str, name: str) -> str:
    """"rt/<ns>/<name>" for a relative name; an absolute "/name" ignores the namespace."""
    if name.startswith("/"):
        return "rt" + name
    ns = namespace.strip("/")
    return f"rt/{ns}/{name}" if ns else f"rt/{name}"


def gid(entity: Any) -> Any:
    """An entity's GUID as rmw_dds_common/msg/Gid (16 bytes)."""
    return msg("rmw_dds_common/msg/Gid")(data=list(entity.guid.bytes))


class Node:
    """One participant, one node: writers and readers created through it are announced."""

    def __init__(self, name: str, namespace: str = "/", domain_id: int = 0) -> None:
        self.name = name
        self.namespace = "/" + namespace.strip("/")
        self.participant = participant(domain_id, Qos(Policy.Userdata(b"enclave=/;")))
        self._topics: dict[tuple[str, str], Topic] = {}
        self._readers: list[Any] = []
        self._writers: list[Any] = []
        info_type = msg(DISCOVERY_TYPE)
        self._info_topic = Topic(self.participant, DISCOVERY_TOPIC, info_type)
        self._info_writer = DataWriter(self.participant, self._info_topic, qos=dds_qos(DISCOVERY, None))

    def _topic(self, name: str, type_name: str) -> Topic:
        full = topic_name(self.namespace, name)
        topic = self._topics.get((full, type_name))
        if topic is None:
            topic = self._topics[full, type_name] = Topic(self.participant, full, msg(type_name))
        return topic

    def writer(self, name: str, type_name: str, profile: QosProfile = DEFAULT) -> DataWriter:
        w = DataWriter(self.participant, self._topic(name, type_name), qos=dds_qos(profile, type_name))
        self._writers.append(w)
        return w

    def reader(self, name: str, type_name: str, profile: QosProfile = DEFAULT) -> DataReader:
        r = DataReader(self.participant, self._topic(name, type_name), qos=dds_qos(profile, type_name))
        self._readers.append(r)
        return r

    def announce(self) -> None:
        """Publish this node and its endpoints on ros_discovery_info (after creating them)."""
        node = msg("rmw_dds_common/msg/NodeEntitiesInfo")(
            node_namespace=self.namespace, node_name=self.name,
            reader_gid_seq=[gid(r) for r in self._readers], writer_gid_seq=[gid(w) for w in self._writers])
        info = msg(DISCOVERY_TYPE)(gid=gid(self.participant), node_entities_info_seq=[node])
        self._info_writer.write(info)
