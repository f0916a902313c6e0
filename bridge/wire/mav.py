"""The one place that imports pymavlink: MAVLink 2, the `ardupilotmega` dialect (all of
`common`, plus ArduPilot's own messages: SIMSTATE is its simulator's true attitude).

pymavlink picks MAVLink 1 or 2 from the MAVLINK20 environment variable at import time,
so it must be set before the first import anywhere in the process.
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import ardupilotmega as mavlink

MAVLink = mavlink.MAVLink
MAVLinkMessage = mavlink.MAVLink_message

#: Default component id of the bridge (MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY..., PX4's
#: "onboard computer" range is 191..194; 191 = MAV_COMP_ID_ONBOARD_COMPUTER).
BRIDGE_COMPONENT_ID = 191

__all__ = ["BRIDGE_COMPONENT_ID", "MAVLink", "MAVLinkMessage", "mavlink"]
