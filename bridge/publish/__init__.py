"""Publish: what leaves the bridge. ATTITUDE_QUATERNION / ATTITUDE back over MAVLink
(output), JSON over MQTT (mqtt), the session recorded as a tlog (record). May import
``wire``, ``vehicle`` and ``estimate``. A new output goes here."""
