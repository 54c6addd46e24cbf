"""A device's channels worked together (lathed.analysis.device_rows): each channel's cut state
the same, bit for bit, as its own alone; one channel's bad data or stopped reader leaves the
others as they were."""
from __future__ import annotations

import numpy as np
import pytest

from lathed.analysis.conditioning import Conditioner, ConditionerBank
from lathed.analysis.cut.sources import VibrationCutDetector
from lathed.analysis.device_rows import DeviceRows
from lathed.analysis.regen import Segment as S, simulate_cut
from lathed.sim.lathe import LATHE_KF, LATHE_MODES

RATE = 51200.0
BLOCK = 1024


def _signals(n: int, cut_s: float = 0.4) -> np.ndarray:
    """Frames x channels, full scale: cuts entering and leaving at different times and gains."""
    cols = []
    for i in range(n):
        rec = simulate_cut([S(0.2 + 0.05 * i, 3000, 0.0), S(cut_s, 3000, 0.6 + 0.1 * i), S(0.5, 3000, 0.0)],
                           modes=LATHE_MODES, kf_n_per_m2=LATHE_KF, seed=10 + i)
        cols.append(rec.signal[:int((0.65 + cut_s) * RATE)] / (40.0 * (i + 1)))
    return np.stack(cols, axis=1).astype(np.float32)


def _state(det: VibrationCutDetector) -> bytes:
    # everything the detector says or carries on, as bytes (NaN compared as itself)
    nums = [det.floor, det.entry_jump, *det._last_rms, det._quiet, det._run,
            -1 if det.contact is None else det.contact, {None: -1, False: 0, True: 1}[det.cutting]]
    return np.array(nums, float).tobytes() + np.asarray(det._rest, float).tobytes()


class Counted(DeviceRows):
    served = 0

    def frame_rms(self, frame, k, row):
        got = super().frame_rms(frame, k, row)
        Counted.served += got is not None
        return got


@pytest.fixture
def counted(monkeypatch):
    import lathed.analysis.conditioning as conditioning
    monkeypatch.setattr(conditioning, "DeviceRows", Counted)
    Counted.served = 0
    return Counted


def test_each_channels_cut_state_is_its_own_bit_for_bit(counted):
    x = _signals(4)
    x[int(0.5 * RATE):int(0.5 * RATE) + 300, 1] = np.inf        # one channel's bad data
    bank = ConditionerBank()
    members = ["a", "b", "c", "d"]
    for col, m in enumerate(members):
        bank.join(m, Conditioner(RATE, 9.8 * (col + 1), 2.0), col)
    alone = {m: (Conditioner(RATE, 9.8 * (col + 1), 2.0), VibrationCutDetector(RATE)) for col, m in enumerate(members)}
    shared = {m: VibrationCutDetector(RATE) for m in members}
    # "d" frames differently: it cannot share the others' frames and works alone throughout
    alone["d"] = (alone["d"][0], VibrationCutDetector(RATE, frame_s=0.003))
    shared["d"] = VibrationCutDetector(RATE, frame_s=0.003)
    entries = dict.fromkeys(members, 0)
    blocks = len(x) // BLOCK
    for b in range(blocks):
        data = x[b * BLOCK:(b + 1) * BLOCK].copy()
        if b in (9, 10):
            data[:, 2] = 0.0          # digital silence on "c": its row is not in the block's rows
        for m in members:
            _, _, y, at = bank.take(m, data)
            cond, det = alone[m]
            if y is None:
                assert at is None
                continue
            own = cond.process(np.ascontiguousarray(data[:, members.index(m)]))
            assert own.tobytes() == y.tobytes()
            if m == "b" and 20 <= b < 24:
                continue              # "b"'s reader stopped a while (restarted: a fresh detector)
            if m == "b" and b == 24:
                alone["b"] = (cond, VibrationCutDetector(RATE))
                shared["b"] = VibrationCutDetector(RATE)
                det = alone["b"][1]
            rows, row = at
            assert rows.ys[row] is y
            got = shared[m].process(y, rows, row)
            want = det.process(own)
            entries[m] += want is not None
            assert got == want and _state(shared[m]) == _state(det), (m, b)
    # the cuts' entries and exits were in it ("b" is blind from its bad data on)
    assert entries["a"] >= 2 and entries["c"] >= 2 and entries["d"] >= 2, entries
    # each was served with the others that frame alike but for its first block and the one
    # after it missed blocks ("c"'s silence, "b"'s stop, each then at its own offset)
    assert counted.served >= 4 * blocks - 4 - 2 - 2 - 4 - 2


def test_a_reader_two_blocks_behind_works_alone():
    # the rows keep the two latest blocks: an older block's frames are not made together
    x = _signals(2)
    bank = ConditionerBank()
    for col, m in enumerate("ab"):
        bank.join(m, Conditioner(RATE, 9.8, 2.0), col)
    got = [bank.take("a", x[b * BLOCK:(b + 1) * BLOCK])[3][0] for b in range(4)]
    assert got[0].ys is None and got[1].ys is None and got[2].prev is None
    assert got[3].prev is got[2] and got[2].ys is not None
    got[2].ask(204, 12, 0)
    assert got[3].frame_rms(204, 12, 0) is not None
    assert got[3].frame_rms(205, 12, 0) is None and got[3].frame_rms(204, 12, 1) is None   # not asked
    got[1].ask(204, 8, 0)
    assert got[2].frame_rms(204, 8, 0) is None      # its block before is let go


def _run_channels(device: str, fail_at: int | None) -> tuple[dict[str, list], list, object]:
    """Three audio_input sensors on one device, each with a chatter analyzer (the shipped table,
    the cut from the vibration) fed by bus taps, in one process; the second analyzer's block
    handling raises at block ``fail_at``. Returns each analyzer's published samples, the
    analyzers' run() outcomes and the bus."""
    import asyncio
    import tomllib
    from pathlib import Path

    import structlog

    from lathed.analyzer import AnalyzerContext
    from lathed.bus import Bus, Sample
    from lathed.config import Section
    from lathed.driver import DriverContext
    from lathed_plugins.audio_input import AudioInput
    from lathed_plugins.chatter import ChatterAnalyzer

    table = tomllib.loads((Path(__file__).parent.parent / "etc" / "lathed.toml").read_text())["analyzer"]["chatter"]
    table = {k: v for k, v in table.items() if k not in ("dwell_axes", "dwell_max")}
    log = structlog.get_logger("test")
    bus = Bus()
    out: dict[str, list] = {f"chatter{k}": [] for k in (1, 2, 3)}
    publish = bus.publish

    def keep(msg):
        if msg.source in out and isinstance(msg, Sample) and msg.quantity != "blind":
            out[msg.source].append((msg.quantity, msg.value, msg.t))
        publish(msg)
    bus.publish = keep
    listeners, sensors, analyzers = [], [], []

    async def attach(sensor, on_block, on_gone, stall_s):
        listeners.append(on_block)
        return {"name": device, "hostapi": "none", "latency_s": 0.01, "pid": 0}

    for k in (1, 2, 3):
        drv = AudioInput(f"accel{k}", Section("t.toml", f"sensor.accel{k}", {
            "device": device, "rate": RATE, "block": BLOCK, "channel": k, "sensitivity_mv_g": 100.0,
            "full_scale_v": 5.0}))
        drv.dev.attach = attach
        drv.ctx = DriverContext(bus, log, lambda *a: None)
        sensors.append(drv)
        an = ChatterAnalyzer(f"chatter{k}", Section("t.toml", f"analyzer.chatter{k}", {
            **table, "input": f"accel{k}", "cut_from": ["vibration"]}))
        an.ctx = AnalyzerContext(bus, log, lambda *a: None, None, lambda *a: None, None,
                                 lambda name: {"state": "connected"}, ".")
        analyzers.append(an)
    blocks = [0]
    if fail_at is not None:
        own = analyzers[1]._on_block

        def failing(b):
            if blocks[0] >= fail_at:
                raise RuntimeError("a bug in chatter2")
            own(b)
        analyzers[1]._on_block = failing
    x = _signals(3, cut_s=1.2)

    async def run():
        for drv in sensors:
            await drv.connect()
        tasks = [asyncio.create_task(an.run()) for an in analyzers]
        await asyncio.sleep(0)
        bus.publish(Sample("lathe", "spindle_rpm", 3000.0, "r/min", 0.0))
        for b in range(len(x) // BLOCK):
            blocks[0] = b
            meta = {"adc": b * BLOCK / RATE, "host_t": 100.0 + b * BLOCK / RATE, "overflow": False, "dropped": 0}
            for on_block in listeners:
                on_block(np.ascontiguousarray(x[b * BLOCK:(b + 1) * BLOCK]), meta)
            await asyncio.sleep(0)
        done = [t.done() for t in tasks]
        for t in tasks:
            t.cancel()
        res = await asyncio.gather(*tasks, return_exceptions=True)
        return [(d, r) for d, r in zip(done, res)]
    return out, asyncio.run(run()), bus


def test_one_channels_failing_analyzer_leaves_the_others_as_they_were():
    calm, outcome, _ = _run_channels("rows-calm", None)
    assert all(not done for done, _ in outcome)
    broken, outcome, bus = _run_channels("rows-broken", 30)
    # the failure is the second analyzer's own: its run() ends with it (the supervisor restarts
    # it), the bus counts no tap failure, the others publish what they published without it
    (d1, _), (d2, err), (d3, _) = outcome
    assert d2 and isinstance(err, RuntimeError) and not d1 and not d3
    assert bus.tap_failures == 0
    for name in ("chatter1", "chatter3"):
        assert sum(q == "chatter_index" for q, _, _ in calm[name]) > 20
        assert broken[name] == calm[name], name
    n = len(broken["chatter2"])
    assert 0 < n < len(calm["chatter2"]) and broken["chatter2"] == calm["chatter2"][:n]
