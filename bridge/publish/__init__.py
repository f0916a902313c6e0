"""Publish: what leaves the bridge. ATTITUDE_QUATERNION / ATTITUDE back over MAVLink
(output), JSON over MQTT (mqtt: the connection, estimates: every estimator's attitude,
presence: each vehicle's online state), the session recorded as a tlog (record), the
live web view (web, fed by snapshot; its page in webview/). May import ``wire``,
``vehicle`` and ``estimate``. A new output goes here."""
