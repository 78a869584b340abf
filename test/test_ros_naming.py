"""ROS 2 Jazzy name, type-name and type-hash conventions (rmw_cyclonedds_cpp)."""

import re

import pytest

from t42_transfer.ros import naming, qos
from t42_transfer.ros.naming import (
    dds_reply_topic,
    dds_request_topic,
    dds_request_type_name,
    dds_response_type_name,
    dds_topic,
    dds_type_name,
    type_hash,
    user_data_typehash,
)

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
PROJECT_TYPES = {
    "geometry_msgs/msg/PoseStamped": "geometry_msgs::msg::dds_::PoseStamped_",
    "sensor_msgs/msg/JointState": "sensor_msgs::msg::dds_::JointState_",
    "trajectory_msgs/msg/JointTrajectory": "trajectory_msgs::msg::dds_::JointTrajectory_",
    "geometry_msgs/msg/PointStamped": "geometry_msgs::msg::dds_::PointStamped_",
    "nav_msgs/msg/Path": "nav_msgs::msg::dds_::Path_",
    "diagnostic_msgs/msg/DiagnosticArray": "diagnostic_msgs::msg::dds_::DiagnosticArray_",
    "std_msgs/msg/String": "std_msgs::msg::dds_::String_",
}


def test_topic_and_service_names():
    assert dds_topic("/hand/object_pose") == "rt/hand/object_pose"
    assert dds_topic("/chatter") == "rt/chatter"
    assert dds_request_topic("/hand/reset") == "rq/hand/resetRequest"
    assert dds_reply_topic("/hand/reset") == "rr/hand/resetReply"


def test_hand_topics_are_valid():
    from msg_adapters import HAND_TOPICS

    for topic in HAND_TOPICS:
        assert dds_topic(topic) == "rt" + topic


@pytest.mark.parametrize(
    "bad",
    ["", "/", "hand/pose", "/hand/", "/hand//pose", "/1hand", "/hand/2pose", "/ha nd", "/hand-pose",
     "/hand/pöse", "~/pose", "/{node}/pose", "/hand__pose", None],
)
def test_bad_names_refused(bad):
    with pytest.raises(ValueError):
        dds_topic(bad)
    with pytest.raises(ValueError):
        dds_request_topic(bad)


@pytest.mark.parametrize("msgtype,dds", sorted(PROJECT_TYPES.items()))
def test_project_type_names_and_hashes(msgtype, dds):
    assert dds_type_name(msgtype) == dds
    assert re.fullmatch(r"RIHS01_[0-9a-f]{64}", type_hash(msgtype))
    assert user_data_typehash(msgtype) == f"typehash={type_hash(msgtype)};"


def test_known_string_hash():
    assert type_hash("std_msgs/msg/String") == STRING_HASH
    assert user_data_typehash("std_msgs/msg/String") == f"typehash={STRING_HASH};"


def test_service_type_names():
    assert dds_request_type_name("std_srvs/srv/Trigger") == "std_srvs::srv::dds_::Trigger_Request_"
    assert dds_response_type_name("std_srvs/srv/Trigger") == "std_srvs::srv::dds_::Trigger_Response_"
    assert naming.request_type("std_srvs/srv/Trigger") == "std_srvs/srv/Trigger_Request"
    for t in ("std_srvs/srv/Trigger_Request", "std_srvs/srv/Trigger_Response"):
        assert re.fullmatch(r"RIHS01_[0-9a-f]{64}", type_hash(t))
    fields = [name for name, _ in naming.SRV_TYPESTORE.fielddefs["std_srvs/srv/Trigger_Response"][1]]
    assert fields == ["success", "message"]


@pytest.mark.parametrize("bad", ["PoseStamped", "geometry_msgs/PoseStamped", "geometry_msgs/srv/PoseStamped",
                                 "geometry_msgs::msg::PoseStamped", "a/msg/b/c"])
def test_bad_type_names_refused(bad):
    with pytest.raises(ValueError):
        dds_type_name(bad)


def test_service_type_name_needs_srv():
    with pytest.raises(ValueError):
        dds_request_type_name("std_msgs/msg/String")


def test_unknown_type_hash():
    with pytest.raises(KeyError):
        type_hash("nope_msgs/msg/Nope")


def test_qos_presets():
    assert (qos.DEFAULT.history, qos.DEFAULT.depth, qos.DEFAULT.reliability, qos.DEFAULT.durability) == (
        qos.History.KEEP_LAST, 10, qos.Reliability.RELIABLE, qos.Durability.VOLATILE)
    assert (qos.SENSOR_DATA.depth, qos.SENSOR_DATA.reliability, qos.SENSOR_DATA.durability) == (
        5, qos.Reliability.BEST_EFFORT, qos.Durability.VOLATILE)
    assert (qos.TRANSIENT_LOCAL.depth, qos.TRANSIENT_LOCAL.reliability, qos.TRANSIENT_LOCAL.durability) == (
        1, qos.Reliability.RELIABLE, qos.Durability.TRANSIENT_LOCAL)
    with pytest.raises(Exception):
        qos.DEFAULT.depth = 3
    with pytest.raises(ValueError):
        qos.QoSProfile(depth=0)
    assert qos.DEFAULT.compatible_with(qos.SENSOR_DATA)
    assert not qos.SENSOR_DATA.compatible_with(qos.DEFAULT)
    assert not qos.DEFAULT.compatible_with(qos.TRANSIENT_LOCAL)
