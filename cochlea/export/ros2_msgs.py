"""The ROS 2 message definitions ``cochlea-mcap`` writes, as schema text (``ros2msg``), so that
no ROS installation is needed to write or read the MCAP file.

Each type's text is its standard ``.msg`` definition (the fields and constants of ROS 2 Humble
and later, comments left out), followed by the definitions of every type it uses, each after a
line of 80 ``=`` and a ``MSG: package/Type`` line: the form ``ros2 bag record`` stores in an
MCAP schema record, which Foxglove and ``ros2 bag`` (rosbag2_storage_mcap) both read.
"""

from __future__ import annotations

#: package/Type -> the standard definition (fields in order; same-package types unqualified).
DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/MultiArrayDimension": "string label\nuint32 size\nuint32 stride\n",
    "std_msgs/MultiArrayLayout": "MultiArrayDimension[] dim\nuint32 data_offset\n",
    "std_msgs/Float64MultiArray": "MultiArrayLayout layout\nfloat64[] data\n",
    "sensor_msgs/JointState": ("std_msgs/Header header\nstring[] name\nfloat64[] position\n"
                               "float64[] velocity\nfloat64[] effort\n"),
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\nPose pose\n",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/TransformStamped": ("std_msgs/Header header\nstring child_frame_id\n"
                                       "Transform transform\n"),
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "rcl_interfaces/Log": ("byte DEBUG=10\nbyte INFO=20\nbyte WARN=30\nbyte ERROR=40\n"
                           "byte FATAL=50\nbuiltin_interfaces/Time stamp\nuint8 level\n"
                           "string name\nstring msg\nstring file\nstring function\n"
                           "uint32 line\n"),
}

PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
              "int32", "uint32", "int64", "uint64", "string", "wstring"}
SEPARATOR = "=" * 80


def _uses(name: str) -> list[str]:
    """The message types ``name``'s fields use, fully qualified, in field order."""
    package = name.split("/")[0]
    used = []
    for line in DEFINITIONS[name].splitlines():
        words = line.split()
        if not words or "=" in words[1]:
            continue  # a constant
        kind = words[0].split("[")[0]
        if kind in PRIMITIVES or kind.startswith(("string<", "wstring<")):
            continue
        used.append(kind if "/" in kind else f"{package}/{kind}")
    return used


def dependencies(name: str) -> list[str]:
    """Every type ``name`` needs, each once, depth first in field order (as rosbag2 lists
    them)."""
    found: list[str] = []

    def visit(type_name: str) -> None:
        for dep in _uses(type_name):
            if dep not in found:
                found.append(dep)
                visit(dep)

    visit(name)
    return found


def schema_name(name: str) -> str:
    """The MCAP schema name of a type: ``package/msg/Type``."""
    package, type_name = name.split("/")
    return f"{package}/msg/{type_name}"


def schema_text(name: str) -> str:
    """The ``ros2msg`` schema text of ``name`` (``package/Type``) with its dependencies."""
    parts = [DEFINITIONS[name]]
    for dep in dependencies(name):
        parts.append(f"{SEPARATOR}\nMSG: {dep}\n{DEFINITIONS[dep]}")
    return "\n".join(parts)
