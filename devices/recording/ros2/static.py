"""A fixed transform as ROS 2 text: a ``static_transform_publisher`` launch snippet and a URDF joint (ADR 0020)."""

from __future__ import annotations

from collections.abc import Sequence
from xml.sax.saxutils import quoteattr

from cellcal.devices.pose import Pose

__all__ = ["launch_file", "launch_snippet", "urdf_joint"]


def _num(value: float) -> str:
    """A float as its shortest round-trip text (the exact value, no rounding)."""
    return repr(float(value))


def _one_line(note: str) -> str:
    """``note`` as one line that is safe in a Python comment and in an XML comment."""
    text = "".join(c if c.isprintable() else "?" for c in note)
    while "--" in text:
        text = text.replace("--", "- -")
    return text


def launch_snippet(pose: Pose, parent: str, child: str, *, node_name: str = "cellcal_mount",
                   note: str | None = None) -> str:
    """A ROS 2 Python launch file publishing ``T_parent_child`` with tf2's ``static_transform_publisher``.

    Uses the named arguments of ROS 2 Humble and later (``--x ... --qw``, ``--frame-id``,
    ``--child-frame-id``): translation in metres, rotation as the quaternion x, y, z, w.
    ``note`` (e.g. that the transform was configured, not estimated) becomes a ``# NOTE:``
    comment line after the first.
    """
    return launch_file([(pose, parent, child, node_name, note)])


def launch_file(transforms: Sequence[tuple[Pose, str, str, str, str | None]]) -> str:
    """One ROS 2 launch file with a ``static_transform_publisher`` per ``(pose, parent, child, node, note)``.

    Each transform's header comment gives its ``ros2 run`` line and its note; node names must differ.
    """
    head, nodes = [], []
    for pose, parent, child, node_name, note in transforms:
        x, y, z = (_num(v) for v in pose.translation)
        qx, qy, qz, qw = (_num(v) for v in pose.rotation.as_quat())
        args = (f'"--x", "{x}", "--y", "{y}", "--z", "{z}",\n'
                f'                       "--qx", "{qx}", "--qy", "{qy}", "--qz", "{qz}", "--qw", "{qw}",\n'
                f'                       "--frame-id", "{parent}", "--child-frame-id", "{child}"')
        head.append(f"# {parent} -> {child}: publish with 'ros2 launch' (or 'ros2 run tf2_ros "
                    f"static_transform_publisher --x {x} --y {y} --z {z} --qx {qx} --qy {qy} --qz {qz} --qw {qw}"
                    f" --frame-id {parent} --child-frame-id {child}')\n"
                    + (f"# NOTE: {_one_line(note)}\n" if note else ""))
        nodes.append(f'        Node(package="tf2_ros", executable="static_transform_publisher", name="{node_name}",\n'
                     f"             arguments=[{args}]),\n")
    return ("".join(head) + "from launch import LaunchDescription\n"
            "from launch_ros.actions import Node\n\n\n"
            "def generate_launch_description():\n"
            "    return LaunchDescription([\n" + "".join(nodes) + "    ])\n")


def urdf_joint(pose: Pose, parent: str, child: str, *, name: str | None = None, note: str | None = None) -> str:
    """A fixed URDF joint placing ``child`` at ``T_parent_child``: ``xyz`` in metres, ``rpy`` in radians.

    URDF's ``rpy`` is fixed-axis roll, pitch, yaw — :meth:`Pose.as_xyz_rpy`'s convention.
    ``note`` becomes an XML comment ``<!-- NOTE: ... -->`` before the joint.
    """
    xyz_rpy = pose.as_xyz_rpy()
    xyz = " ".join(_num(v) for v in xyz_rpy[:3])
    rpy = " ".join(_num(v) for v in xyz_rpy[3:])
    joint = name or f"{parent}_to_{child}"
    return ((f"<!-- NOTE: {_one_line(note)} -->\n" if note else "")
            + f"<joint name={quoteattr(joint)} type=\"fixed\">\n"
            f"  <parent link={quoteattr(parent)}/>\n"
            f"  <child link={quoteattr(child)}/>\n"
            f"  <origin xyz=\"{xyz}\" rpy=\"{rpy}\"/>\n"
            "</joint>\n")
