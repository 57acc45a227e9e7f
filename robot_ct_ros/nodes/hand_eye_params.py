"""What the acquisition nodes share: the hand-eye parameters and pose/stamp conversions (m <-> mm, and
PoseStamped <-> UR pose for the arm_driver).

Hand-eye parameters (identical in pcd_grabber, geometry_publisher and scan_orchestrator;
config/hand_eye.yaml sets them for all nodes at once), per device ``source`` and ``detector``:

  hand_eye.<device>.translation_m   [x, y, z] metres, TCP frame -> device frame origin
  hand_eye.<device>.rotvec_rad      [rx, ry, rz] rotation vector, rad     } give one of them, as floats;
  hand_eye.<device>.rpy_rad         [roll, pitch, yaw] rad (R = Rz Ry Rx) } neither: the default mount
                                    (each an empty array, unset, when not given)

The device frames are defined in :mod:`robot_ct_ros.ct.hand_eye` (defaults: focal spot 0.12 m
along tool +z with the beam along tool +z; detector centre 0.08 m along tool +z facing out).
"""

from __future__ import annotations

import numpy as np
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation

from robot_ct_ros.ct.hand_eye import HandEye, mount_from_si

__all__ = ["declare_hand_eye", "stamp_to_ns", "ns_to_stamp", "check_pose", "pose_to_matrix_mm", "matrix_mm_to_pose",
           "pose_msg_to_ur", "ur_to_pose_msg", "QUATERNION_TOLERANCE"]

QUATERNION_TOLERANCE = 1e-3
"""How far from 1 the norm of an incoming orientation quaternion may be (as the bag reader accepts)."""


def declare_hand_eye(node, prefix: str = "hand_eye") -> HandEye:
    """Declare the hand-eye parameters on ``node`` and return the mounts (raises ValueError if invalid)."""
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    from robot_ct_ros.nodes.common import (READ_AT_START, declare_optional_array, refuse_mistyped_file_value,
                                           whole_numbers_as_doubles)

    def declare(name, value):
        whole_numbers_as_doubles(node, name, "double_array")
        refuse_mistyped_file_value(node, name, Parameter.Type.DOUBLE_ARRAY)
        desc = ParameterDescriptor(name=name, description=f"hand-eye mount of the device on its flange"
                                   f"{' ([] = unset)' if value is None else ''}.{READ_AT_START}", read_only=True)
        try:
            if value is None:  # optional: an empty array (unset) unless given
                return list(declare_optional_array(node, name, Parameter.Type.DOUBLE_ARRAY, desc).value) or None
            return node.declare_parameter(name, value, desc).value
        except (InvalidParameterTypeException, InvalidParameterValueException, TypeError) as exc:
            raise ValueError(f"parameter {name}: {exc}") from None

    default = HandEye()
    mounts = {}
    for dev in ("source", "detector"):
        base = getattr(default, dev)
        t = declare(f"{prefix}.{dev}.translation_m", [x * 1e-3 for x in base.translation_mm])
        rv = declare(f"{prefix}.{dev}.rotvec_rad", None)
        rpy = declare(f"{prefix}.{dev}.rpy_rad", None)
        if rv is None and rpy is None:
            rv = list(base.rotvec)
        mounts[dev] = mount_from_si(list(t), rv, rpy, what=f"{prefix}.{dev}")
    return HandEye(**mounts)


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int):
    from builtin_interfaces.msg import Time

    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def check_pose(pose) -> tuple[np.ndarray, np.ndarray]:
    """(position m, unit quaternion x, y, z, w) of an incoming geometry_msgs/Pose: what every node
    checks at its boundary before using a pose.

    Raises
    ------
    ValueError
        A NaN or infinite value, or an orientation quaternion whose norm is not 1 (within
        :data:`QUATERNION_TOLERANCE`): a scaled or zero quaternion is a sender's bug, never
        silently normalised.
    """
    p, o = pose.position, pose.orientation
    xyz = np.array([p.x, p.y, p.z], dtype=float)
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    if not np.all(np.isfinite(xyz)):
        raise ValueError(f"pose position is not finite ({xyz.tolist()})")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"pose orientation quaternion is not finite ({q.tolist()})")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > QUATERNION_TOLERANCE:
        raise ValueError(f"pose orientation quaternion is not a unit quaternion (norm {n:.6g})")
    return xyz, q / n


def pose_to_matrix_mm(pose) -> np.ndarray:
    """geometry_msgs/Pose (metres, quaternion) -> 4 x 4 matrix in mm (ValueError: :func:`check_pose`)."""
    xyz, q = check_pose(pose)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = xyz * 1e3
    if not np.all(np.isfinite(T)):  # finite metres beyond ~1e305 overflow in mm
        raise ValueError("pose position is out of range")
    return T


def matrix_mm_to_pose(T, pose=None):
    """4 x 4 matrix in mm -> geometry_msgs/Pose (metres, quaternion with w >= 0)."""
    from geometry_msgs.msg import Pose

    pose = Pose() if pose is None else pose
    T = np.asarray(T, dtype=float)
    x, y, z = (float(v) * 1e-3 for v in T[:3, 3])
    pose.position.x, pose.position.y, pose.position.z = x, y, z
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


def pose_msg_to_ur(msg, frame_id: str | None = None) -> np.ndarray:
    """The UR pose [x, y, z, rx, ry, rz] (m, rad) of a geometry_msgs/PoseStamped; ValueError when it holds a
    NaN or infinite value or a quaternion whose norm is not 1 (:func:`check_pose`), or, given ``frame_id``,
    when its frame_id is neither that nor empty."""
    if frame_id is not None and msg.header.frame_id not in ("", frame_id):
        raise ValueError(f"frame {msg.header.frame_id!r} is not {frame_id!r}")
    xyz, q = check_pose(msg.pose)
    return np.array([*xyz, *Rotation.from_quat(q).as_rotvec()])


def ur_to_pose_msg(pose, frame_id: str, stamp):
    """geometry_msgs/PoseStamped of a UR pose [x, y, z, rx, ry, rz] (m, rad), with this frame_id and stamp."""
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in pose[:3])
    x, y, z, w = Rotation.from_rotvec(pose[3:6]).as_quat()
    msg.pose.orientation.x, msg.pose.orientation.y = float(x), float(y)
    msg.pose.orientation.z, msg.pose.orientation.w = float(z), float(w)
    return msg
