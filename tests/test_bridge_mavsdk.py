"""A real MAVSDK 4.x client (native binding) reads the bridge's attitude output."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from bridge_support import (
    MavSender,
    async_test,
    euler_q,
    free_udp_port,
    running_bridge,
    send_rotating,
)
from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk
from mavsdk.plugins.telemetry import Telemetry

from estimators import quat as Q

#: mostly waits on real time: spread among computing tests (conftest)
pytestmark = pytest.mark.realtime


@async_test
async def test_mavsdk_reads_quaternion_and_euler():
    port = free_udp_port()
    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    assert sdk.add_any_connection(f"udpin://127.0.0.1:{port}") == ConnectionResult.SUCCESS
    quats, eulers = [], []  # appended from MAVSDK's own threads
    q0 = euler_q(10.0, -20.0, 45.0)
    async with running_bridge(outs=[f"udpout:127.0.0.1:{port}"], out_rate=50.0) as bridge:
        vehicle = MavSender(bridge.port)
        await vehicle.start()
        stream = asyncio.create_task(send_rotating(vehicle, q0, np.zeros(3), 4.0))
        system = None
        for _ in range(50):  # discovered from the bridge's HEARTBEAT
            await asyncio.sleep(0.1)
            systems = sdk.get_systems()
            if systems:
                system = systems[0]
                break
        assert system is not None
        telemetry = Telemetry(system)
        telemetry.subscribe_attitude_quaternion(lambda q, _: quats.append(q))
        telemetry.subscribe_attitude_euler(lambda e, _: eulers.append(e))
        await stream
        await asyncio.sleep(0.3)
        sysid, components = system.get_system_id(), system.component_ids()
    vehicle.close()
    assert (sysid, components) == (1, [191])
    assert len(quats) > 50 and len(eulers) > 50
    q = quats[-1]
    got = np.array([q.w, q.x, q.y, q.z])
    assert np.degrees(Q.angle_between(got, q0)) < 1.5
    e = eulers[-1]
    roll, pitch, yaw = np.degrees(Q.to_euler(got))
    assert abs(e.roll_deg - roll) < 0.05 and abs(e.pitch_deg - pitch) < 0.05
    assert abs((e.yaw_deg - yaw + 180.0) % 360.0 - 180.0) < 0.05
    assert math.isclose(e.timestamp_us, q.timestamp_us)  # same sample: time_boot_ms
    del telemetry
    sdk.destroy()
