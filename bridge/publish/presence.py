"""Each served vehicle's retained ``<prefix>/<sysid>/online`` on MQTT.

``online`` while its attitude is being published, ``offline`` when its data stopped or
the bridge stopped, and, as the last will of a connection of its own, when the bridge
died. A broker keeps one will per connection, so each vehicle gets its own small
connection beside the main publisher.
"""

from __future__ import annotations

import asyncio
import dataclasses

from .mqtt import MqttPublisher, Outgoing


class MqttPresence:
    """The per-vehicle presence connections, opened on a vehicle's first state."""

    def __init__(self, main: MqttPublisher) -> None:
        self.main = main
        self.publishers: dict[int, MqttPublisher] = {}
        self.tasks: list[asyncio.Task] = []

    def set_online(self, sysid: int, online: bool) -> None:
        """Say (retained) whether ``sysid`` is online; opens its connection first time."""
        presence = self._publisher(sysid)
        presence.set_retained(presence.topic(sysid, "online"),
                              "online" if online else "offline")

    def keep_only(self, served: set[int]) -> None:
        """Vehicles no longer served (a provisional one replaced) are offline."""
        for sysid in self.publishers:
            if sysid not in served:
                self.set_online(sysid, False)

    def all_offline(self) -> None:
        """The bridge stops: every vehicle it has announced is offline."""
        for sysid in self.publishers:
            self.set_online(sysid, False)

    def _publisher(self, sysid: int) -> MqttPublisher:
        presence = self.publishers.get(sysid)
        if presence is None:
            settings = dataclasses.replace(self.main.settings, client_id=None, queue_size=16)
            topic = self.main.topic(sysid, "online")
            presence = self.publishers[sysid] = MqttPublisher(
                settings, will=Outgoing(topic, "offline", True, 1), quiet=True)
            self.tasks.append(asyncio.create_task(presence.run(), name=f"mqtt online {sysid}"))
        return presence
