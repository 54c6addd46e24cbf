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
            await rig.drain()
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
    assert all(b - a == 1024 for a, b in zip(seqs, seqs[1:])), np.diff(seqs)
    assert all(b.rate_hz == RATE and b.quantity == "acceleration" and b.rpm is None for b in got)
    x = np.concatenate([b.data for b in got]).astype(float)
    # 0.5 of full scale, 5 V full scale, 100 mV/g: 0.5 * 5 / 0.1 g
    amp = np.sqrt(2) * x.std()
    assert amp == pytest.approx(0.5 * 5 / 0.1 * G0, rel=0.01)
    assert abs(x.mean()) < 0.01 * amp              # the DC offset is gone
    # dated on the host's clock: the first block began within a block and the latency of now
    assert abs(got[0].t0 - t_wall) < 0.2
    # the line along the callbacks' stamps dates each block from its index: a block later,
    # within the few milliseconds a new stamp moves the line, not the stamps' own jitter;
    # but for a step the clocks took (the dummy backend's server stalled on this busy
    # machine: a device that stopped for a while), which is counted
    off = np.diff([b.t0 for b in got]) - 1024 / RATE
    assert len(off[off > 0.01]) <= st["clock_steps"] and np.all(off > -0.01), off
    assert st["device"] == "system" and st["hostapi"] == "JACK Audio Connection Kit"
    assert st["lost_samples"] == 0 and st["clipped_samples"] == 0
    assert st["calibration"] == "100 mV/g, interface full scale 5 V"


def test_digital_silence_is_no_signal_not_a_calm_one(jack_server, monkeypatch):
    """An input with nothing connected gives exact zeros: counted, said once, not published
    (an analyzer is blind then, not calm)."""
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    drv = sensor()

    async def main():
        rig = Rig(drv)
        await rig.start()
        try:
            async with asyncio.timeout(20):
                while drv.status()["silent_blocks"] < 20:
                    await asyncio.sleep(0.05)
            return drv.status(), [m for m in list(rig.sub._items) if isinstance(m, Block)]
        finally:
            await rig.stop()
    st, blocks = asyncio.run(main())
    assert blocks == [] and st["blocks"] == 0 and st["samples"] >= 20 * 1024


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


def pulses(rpm: float, seconds: float, rate: int = RATE, amp: float = 0.8) -> np.ndarray:
    """A once-per-revolution mark as an AC-coupled input shows it: a spike up at its edge."""
    n = int(seconds * rate)
    x = np.zeros(n)
    per = rate * 60.0 / rpm
    for k in range(int(n / per) + 1):
        i = int(round(k * per))
        x[i:i + 24] += amp * np.exp(-np.arange(len(x[i:i + 24])) / 6.0)
    return x


def test_keyphasor_channel_gives_the_speed_on_the_device_clock(jack_server, monkeypatch):
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    drv = sensor(keyphasor_channel=2)
    noise = np.random.default_rng(1).normal(0, 0.05, RATE)

    async def main():
        rig = Rig(drv)
        await rig.start()
        player = Player(jack_server, channels=2, idle=np.column_stack([noise, pulses(1500, 1.0)]))
        try:
            player.connect()
            await rig.drain()
            await rig.blocks(0.5)
            await rig.drain()
            at_1500 = await rig.blocks(1.0)
            player.play(np.column_stack([np.tile(noise, 3), pulses(1800, 3.0)]))
            await rig.blocks(1.0)          # the segment reaches the capture
            at_1800 = await rig.blocks(1.0)
            return at_1500, at_1800, drv.status()
        finally:
            player.close()
            await rig.stop()
    at_1500, at_1800, st = asyncio.run(main())
    # 1920 and 1600 samples a revolution, the edges found to a fraction of a sample
    assert all(b.rpm == pytest.approx(1500, rel=2e-4) for b in at_1500), [b.rpm for b in at_1500]
    assert all(b.rpm == pytest.approx(1800, rel=2e-4) for b in at_1800), [b.rpm for b in at_1800]
    assert st["keyphasor_pulses"] > 60


def test_mains_lines_are_notched_and_the_rest_kept(jack_server, monkeypatch):
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    drv = sensor(mains_hz=50)
    t = np.arange(RATE) / RATE
    hum = sum(0.05 * np.sin(2 * np.pi * 50 * k * t + k) for k in (1, 2, 3, 6))
    chatter = 0.2 * np.sin(2 * np.pi * 725 * t)

    async def main():
        rig = Rig(drv)
        await rig.start()
        player = Player(jack_server, idle=hum + chatter)
        try:
            player.connect()
            await rig.drain()
            await rig.blocks(1.0)          # the notches' ring-in (5 time constants)
            await rig.drain()
            return await rig.blocks(2.0)
        finally:
            player.close()
            await rig.stop()
    got = asyncio.run(main())
    x = np.concatenate([b.data for b in got]).astype(float)
    scale = 5 / 0.1 * G0
    spec = np.abs(np.fft.rfft(x * np.hanning(len(x)))) * 4 / len(x) / scale
    f = np.fft.rfftfreq(len(x), 1 / RATE)

    def at(hz):
        return spec[np.argmin(np.abs(f - hz))]
    assert at(725) == pytest.approx(0.2, rel=0.06)                 # within half a dB
    for k in (1, 2, 3, 6):
        assert at(50 * k) < 0.05 / 100, (50 * k, at(50 * k))       # 40 dB down at least


def stalled(drv: AudioInput, server: JackServer, stall, seconds: float):
    """A tone played into ``drv``; ``stall()`` called in the rig's loop after 0.3 s of blocks:
    (the last block before, the blocks of ``seconds`` after, the status, the events)."""
    async def main():
        rig = Rig(drv)
        await rig.start()
        player = Player(server, idle=tone(440, 0.5, 0.1))
        try:
            player.connect()
            await rig.drain()
            before = (await rig.blocks(0.3))[-1]
            stall()
            after = await rig.blocks(seconds)
            return before, after, drv.status(), rig.events
        finally:
            player.close()
            await rig.stop()
    return asyncio.run(main())


def test_blocks_the_daemon_did_not_take_are_counted_and_the_index_keeps_time(jack_server, monkeypatch):
    """A loop held for 3 s (more than the helper holds): blocks are dropped in the helper,
    counted as lost samples, recorded, and the device-clock index jumps by them."""
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    drv = sensor()
    # the fault: an event loop that does not run
    before, after, st, events = stalled(drv, jack_server, lambda: time.sleep(3.0), 5.0)
    seqs = [before.seq] + [b.seq for b in after]
    jumps = [(a, b) for a, b in zip(seqs, seqs[1:]) if b - a != 1024]
    # every jump of the index is samples counted lost (a busy machine may add a gap of its own)
    assert jumps and st["gaps"] == len(jumps), jumps
    assert sum(b - a - 1024 for a, b in jumps) == st["lost_samples"]
    # the held loop's: more than the helper holds (2 s) and the pipe took, less than 3 s
    assert 0.2 * RATE < jumps[0][1] - jumps[0][0] - 1024 < 3 * RATE, jumps
    # the index stays on time: what was lost plus what came is the time that passed (and any
    # step the clocks took: the dummy backend's server stalls on a busy machine)
    assert after[-1].t0 - before.t0 - st["clock_stepped_s"] == pytest.approx((after[-1].seq - before.seq) / RATE,
                                                                             abs=0.05)
    assert "audio_samples_lost" in [k for k, _ in events]


def test_device_gone_is_said_retried_and_back(jack_server, monkeypatch):
    """The audio server stopped (as a USB device pulled): the run ends with 'device gone',
    a reconnection while it is away says so, and once it is back the stream goes on."""
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    drv = sensor(timeout="500ms")

    async def main():
        rig = Rig(drv)
        await rig.start()
        player = Player(jack_server, idle=tone(440, 0.5, 0.1))
        player.connect()
        await rig.drain()
        first = (await rig.blocks(0.3))[-1]
        player.close()
        jack_server.stop()
        with pytest.raises(DeviceGone) as gone:
            await rig.blocks(60.0, timeout=10.0)
        await rig.drv.close()
        with pytest.raises(DeviceGone) as away:
            await rig.drv.connect()
        await rig.drv.close()
        jack_server.start()
        await rig.start()
        player = Player(jack_server, idle=tone(440, 0.5, 0.1))
        player.connect()
        await rig.drain()
        back = await rig.blocks(0.5)
        st = drv.status()
        player.close()
        await rig.stop()
        return first, str(gone.value), str(away.value), back, st
    first, gone, away, back, st = asyncio.run(main())
    assert gone.startswith("device gone: system: ") and "\n" not in gone, gone
    assert away.startswith("device gone: no input device matching 'system'"), away
    assert back[0].seq > first.seq + 1024 and st["helper_starts"] == 3
    assert all(b - a == 1024 for a, b in zip([x.seq for x in back], [x.seq for x in back[1:]]))


def test_two_sensors_share_one_device(jack_server, monkeypatch):
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    a = sensor()
    b = AudioInput("mic", Section("t.toml", "sensor.mic", {"device": "system", "rate": RATE, "channel": 2,
                                                            "sensitivity_mv_pa": 50.0, "full_scale_v": 1.0}))

    async def main():
        ra, rb = Rig(a), Rig(b)
        rb.sub = b.ctx.bus.subscribe("mic", maxsize=100000)
        await ra.start()
        await rb.start()
        player = Player(jack_server, channels=2, idle=np.column_stack([tone(500, 0.1, 0.1), tone(800, 0.1, 0.2)]))
        try:
            player.connect()
            await ra.blocks(0.5)
            await rb.blocks(0.5)
            await ra.drain()
            await rb.drain()
            return await ra.blocks(0.5), await rb.blocks(0.5)
        finally:
            player.close()
            await ra.stop()
            await rb.stop()
    xa, xb = asyncio.run(main())
    assert a.dev is b.dev and a.dev.starts == 1
    assert xb[0].quantity == "sound_pressure"
    ya, yb = (np.concatenate([x.data for x in xs]).astype(float) for xs in (xa, xb))
    assert np.sqrt(2) * ya.std() == pytest.approx(0.1 * 5 / 0.1 * G0, rel=0.02)
    assert np.sqrt(2) * yb.std() == pytest.approx(0.2 * 1 / 0.05, rel=0.02)        # Pa


def test_the_player_plays_on_while_the_test_process_holds_its_gil(jack_server, monkeypatch):
    """The harness: the JACK server waits each period for the player (-S), so a player that
    needs this process's GIL stalled the server whenever a test held it (a full garbage
    collection of a long-lived worker), and the capture rightly said "device gone"."""
    import ctypes
    for k, v in jack_server.env.items():
        monkeypatch.setenv(k, v)
    drv = sensor(timeout="500ms")
    hold = ctypes.PyDLL(None).usleep        # a PyDLL call keeps the GIL for its whole length
    _, after, st, _ = stalled(drv, jack_server, lambda: hold(1_500_000), 1.0)
    assert st["helper_starts"] == 1, st
    assert all(b - a == 1024 for a, b in zip([x.seq for x in after], [x.seq for x in after[1:]]))
