"""The arm a driver's settings name: a UR arm (ur-rtde, in a worker process) or its simulated twin.

Kept apart from :mod:`robot_ct_ros.hardware.arm` (the interface both implement), which neither
implementation may import back.
"""

from __future__ import annotations

from robot_ct_ros.hardware.arm import Arm, ArmSettings
from robot_ct_ros.hardware.simulated_arm import SimulatedArm, SimulatedArmSettings
from robot_ct_ros.hardware.ur_arm import URArm

__all__ = ["make_arm"]


def make_arm(settings: ArmSettings, simulated=None) -> Arm:
    """The arm the settings name: a UR arm at ``settings.robot_ip``, or a simulated arm when it is empty.

    Parameters
    ----------
    settings : ArmSettings
        Address and timeouts.
    simulated : SimulatedArmSettings, optional
        The simulated arm's errors and faults (default: none).

    Returns
    -------
    Arm
        Not yet connected.
    """
    if settings.robot_ip:
        return URArm(settings.robot_ip, connect_timeout_s=settings.connect_timeout_s,
                     call_timeout_s=settings.call_timeout_s, move_timeout_s=settings.move_timeout_s)
    return SimulatedArm.from_settings(simulated or SimulatedArmSettings())
