"""The localization sources, one row each (``bridge.pose_source``, docs/turtlebot-localization.md).

Pure data, so the settings read it without the ROS 2 wire (common/contracts/ros_wire.py, which
decodes the messages, imports rosbags). A row says the source's ROS type, its conventional topic,
the QoS its usual publisher declares, how the robot bridge takes its fixes, and who publishes it
(the TurtleBot3 emulator publishes as that node does). ``odom`` (odometry alone) is no row: it is
the robot's own odometry, with no localization beside it.

QoS: nav2_amcl publishes ``amcl_pose`` reliable, transient local, KeepLast(1) (amcl_node.cpp:
``rclcpp::QoS(rclcpp::KeepLast(1)).transient_local().reliable()``); tf2_ros's listener subscribes
``/tf`` KeepLast(100), reliable, volatile (``DynamicListenerQoS``); robot_localization's
``odometry/filtered`` and a motion-capture ``PoseStamped`` are plain sensor streams (reliable,
volatile, KeepLast(10)).
"""

from __future__ import annotations

from dataclasses import dataclass

ODOMETRY = "nav_msgs/msg/Odometry"
POSE_WITH_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
QOS_DEPTH = 10  # the TurtleBot3's rclcpp::QoS(rclcpp::KeepLast(10)) on cmd_vel and odom
ODOMETRY_ONLY = "odom"  # bridge.pose_source without a localization


@dataclass(frozen=True)
class PoseSource:
    """A localization source's ROS type, conventional topic and publisher QoS, and how the robot
    bridge (services/robot_bridge/bridge.py) takes its fixes. ``map_to_odom``: a fix is the
    ``map -> odom`` transform itself (one of the robot's transforms on ``/tf``), else the robot's
    pose in the map, composed with the odometry at its stamp. ``streams``: fixes come at a rate,
    moving or not; else only after motion (AMCL), so a quiet source is not a stale one. ``node``:
    the ROS node that usually publishes it; ``after_motion``: that node computes a new fix only
    after the robot moved (AMCL's update thresholds), else at its rate. ``what``: for the settings'
    description and the docs."""

    ros_type: str
    topic: str
    depth: int
    transient_local: bool
    node: str
    what: str
    map_to_odom: bool = False
    streams: bool = True
    after_motion: bool = False


POSE_SOURCES: dict[str, PoseSource] = {
    "tf": PoseSource(
        TF_MESSAGE,
        "tf",
        100,
        False,
        "amcl",
        "odom corrected by map -> odom on /tf",
        map_to_odom=True,
        after_motion=True,
    ),
    "pose_with_covariance": PoseSource(
        POSE_WITH_COVARIANCE, "amcl_pose", 1, True, "amcl", "AMCL", streams=False, after_motion=True
    ),
    "odometry": PoseSource(
        ODOMETRY, "odometry/filtered", QOS_DEPTH, False, "ekf_filter_node", "an EKF's nav_msgs/Odometry"
    ),
    "pose_stamped": PoseSource(POSE_STAMPED, "mocap/pose", QOS_DEPTH, False, "mocap", "motion capture"),
}


def pose_source_names() -> tuple[str, ...]:
    """Every value of ``bridge.pose_source``: odometry alone, then the rows."""
    return (ODOMETRY_ONLY, *POSE_SOURCES)


def pose_sources_text() -> str:
    """``odom (odometry only), tf (...), ...``: the settings' description of ``bridge.pose_source``."""
    return ", ".join([f"{ODOMETRY_ONLY} (odometry only)", *(f"{n} ({s.what})" for n, s in POSE_SOURCES.items())])
