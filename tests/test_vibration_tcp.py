"""vibration_tcp: implausible frame headers are refused, counted and skipped; the stream goes on."""
from __future__ import annotations

import asyncio
import math

import numpy as np
import structlog

from lathed.bus import Bus
from lathed.config import Section
from lathed.driver import DriverContext
from lathed.wire import pack_vibration
from lathed_plugins.vibration_tcp import VibrationTCP
from tests.conftest import free_port


def test_nan_rpm_and_1hz_frames_refused_stream_goes_on():
    """issue 18 D5: a frame with rpm NaN or a rate of 1 Hz crash-looped the chatter analyzer."""
    port = free_port()
    x = np.sin(np.arange(256) * 0.1)
    frames = [pack_vibration(0, 1.0, 3000.0, 51200, x), pack_vibration(256, 1.0, math.nan, 51200, x),
              pack_vibration(512, 1.0, 3000.0, 1, x), pack_vibration(768, 1.0, -5.0, 51200, x),
              pack_vibration(1024, 1.0, 3000.0, 51200, x)]

    async def main():
        async def serve(reader, writer):
            writer.write(b"".join(frames))
            await writer.drain()
            await reader.read()          # hold the link open until the driver closes it

        server = await asyncio.start_server(serve, "127.0.0.1", port)
        events = []
        d = VibrationTCP("accel", Section("t.toml", "sensor.accel", {"host": "127.0.0.1", "port": port}))
        d.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: events.append((k, p)))
        sub = d.ctx.bus.subscribe("accel")
        await d.connect()
        task = asyncio.create_task(d.run())
        blocks = []
        while len(blocks) < 2:
            msg = await asyncio.wait_for(sub.get(), 5)
            if hasattr(msg, "data"):
                blocks.append(msg)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await d.close()
        server.close()
        return d, blocks, events

    d, blocks, events = asyncio.run(main())
    assert [b.seq for b in blocks] == [0, 1024] and all(b.rpm == 3000.0 and b.rate_hz == 51200 for b in blocks)
    assert d.status()["refused_frames"] == {"rpm": 2, "rate": 1}
    assert d.lost_samples == 0
    assert {p["reason"] for k, p in events if k == "implausible_value"} == {"rpm", "rate"}
