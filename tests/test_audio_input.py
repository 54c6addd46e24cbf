"""audio_input through a real audio server: a JACK server (dummy backend) reached through
PortAudio by the capture helper, fed by a player client (tests/jack_fixtures.py)."""
from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
import structlog

from lathed.audio_device import AudioDevice, DeviceGone
from lathed.bus import Block, Bus, Sample
from lathed.config import ConfigError, Section
from lathed.driver import DriverContext
from lathed_plugins.audio_input import AudioInput
from tests.jack_fixtures import JackServer, Player, jack_server  # noqa: F401

RATE = 48000
G0 = 9.80665


def sensor(**keys) -> AudioInput:
    cfg = {"device": "system", "rate": RATE, "block": 1024, "sensitivity_mv_g": 100.0, "full_scale_v": 5.0, **keys}
    sec = Section("t.toml", "sensor.accel", cfg)
    d = AudioInput("accel", sec)
    sec.check_unused()
    return d


@pytest.fixture(autouse=True)
def _fresh_devices():
    # each test's sensors claim their own device (one helper per device and process)
    AudioDevice._devices.clear()
    yield
    AudioDevice._devices.clear()


class Rig:
    """The driver on its own loop, as the supervisor runs it: connect, then run in a task."""

    def __init__(self, drv: AudioInput) -> None:
        self.drv = drv
        self.events: list[tuple[str, dict]] = []
        drv.ctx = DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: self.events.append((k, p)))
        self.sub = drv.ctx.bus.subscribe("accel", maxsize=100000)
        self.task: asyncio.Task | None = None

    async def start(self) -> None:
        await self.drv.connect()
        self.task = asyncio.create_task(self.drv.run())

    async def blocks(self, seconds: float, timeout: float = 20.0) -> list[Block]:
        """The blocks of the next ``seconds`` of samples (the driver's run ending raises)."""
        out: list[Block] = []
        async with asyncio.timeout(timeout):
            while sum(len(b.data) for b in out) < seconds * RATE:
                get = asyncio.ensure_future(self.sub.get())
                done, _ = await asyncio.wait({get, self.task}, return_when=asyncio.FIRST_COMPLETED)
                if self.task in done:
                    get.cancel()
                    self.task.result()
                msg = get.result()
                if isinstance(msg, Block):
                    out.append(msg)
        return out

    async def drain(self) -> None:
        while self.sub._items:
            await self.sub.get()

    async def stop(self) -> None:
        if self.task is not None:
            self.task.cancel()
            await asyncio.gather(self.task, return_exceptions=True)
        await self.drv.close()


def tone(hz: float, seconds: float, amp: float, rate: int = RATE) -> np.ndarray:
    return amp * np.sin(2 * np.pi * hz * np.arange(int(seconds * rate)) / rate)


def test_blocks_are_calibrated_dc_free_and_dated_on_both_clocks(jack_server, monkeypatch):
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    drv = sensor()

    async def main():
        rig = Rig(drv)
        await rig.start()
        player = Player(jack_server, idle=0.25 + tone(1000.0, 0.1, 0.5))     # 1 kHz on a DC offset
        try:
            player.connect()
            await rig.blocks(0.5)          # the high-pass settles; the connection's first blocks pass
            await rig.drain()
            t_wall = time.time()
            got = await rig.blocks(2.0)
            return got, t_wall, drv.status()
        finally:
            player.close()
            await rig.stop()
    got, t_wall, st = asyncio.run(main())
    # one stream on the device's clock: consecutive, no sample lost
    seqs = [b.seq for b in got]
    assert all(b - a == 1024 for a, b in zip(seqs, seqs[1:])), seqs
    assert all(b.rate_hz == RATE and b.quantity == "acceleration" and b.rpm is None for b in got)
    x = np.concatenate([b.data for b in got]).astype(float)
    # 0.5 of full scale, 5 V full scale, 100 mV/g: 0.5 * 5 / 0.1 g
    amp = np.sqrt(2) * x.std()
    assert amp == pytest.approx(0.5 * 5 / 0.1 * G0, rel=0.01)
    assert abs(x.mean()) < 0.01 * amp              # the DC offset is gone
    # dated on the host's clock: the first block began within a block and the latency of now
    assert abs(got[0].t0 - t_wall) < 0.2
    # the line through the callbacks' stamps dates each block from its index: a block later
    # (within the millisecond a new stamp moves the line), not the stamps' own jitter
    steps = np.diff([b.t0 for b in got])
    assert np.all(np.abs(steps - 1024 / RATE) < 1e-3), steps
    assert st["device"] == "system" and st["hostapi"] == "JACK Audio Connection Kit"
    assert st["lost_samples"] == 0 and st["clipped_samples"] == 0
    assert st["calibration"] == "100 mV/g, interface full scale 5 V"


def test_unknown_device_is_gone_with_the_devices_listed(jack_server, monkeypatch):
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    drv = sensor(device="333D01")

    async def main():
        rig = Rig(drv)
        with pytest.raises(DeviceGone) as e:
            await rig.drv.connect()
        await rig.drv.close()
        return str(e.value)
    msg = asyncio.run(main())
    assert msg.startswith("device gone: no input device matching '333D01'"), msg
    assert "0: system (JACK Audio Connection Kit, 2 in)" in msg and "\n" not in msg


@pytest.mark.parametrize("keys, problem", [
    ({}, "give one calibration"),
    ({"counts_per_m_s2": 1e4}, "give one calibration"),
    ({"sensitivity_mv_g": None, "counts_per_m_s2": 1e4, "full_scale_v": None, "bits": 12}, "bits: 12 is out of range"),
    ({"keyphasor_channel": 1}, "keyphasor_channel: is the signal's own channel 1"),
    ({"mains_hz": 5}, "mains_hz: 5 Hz is no grid's frequency"),
    ({"device": -1}, "device: expected a device name"),
    ({"sensitivity_mv_g": None, "uncalibrated": False, "full_scale_v": None}, "uncalibrated: false is no calibration"),
])
def test_config_errors_name_the_key(keys, problem):
    cfg = {"device": "system", "sensitivity_mv_g": 100.0, "full_scale_v": 5.0}
    cfg.update(keys)
    cfg = {k: v for k, v in cfg.items() if v is not None}
    if not keys:
        cfg = {"device": "system"}
    with pytest.raises(ConfigError, match=problem):
        AudioInput("accel", Section("t.toml", "sensor.accel", cfg))
