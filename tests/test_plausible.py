"""Every value from a peer is checked for being finite and physically plausible
before it reaches the bus, the machine model or the guard (issue 18 D6/D7)."""
from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
import structlog

from lathed.bus import Block, Bus, Sample
from lathed.config import ConfigError, Section
from lathed.driver import DriverContext
from lathed.plausible import Plausibility
from lathed.wire import format_temperature_line
from lathed_plugins.ds18b20_serial import DS18B20Serial
from lathed_plugins.modbus_cnc import ModbusCNC


def ctx(events=None, plausible=None) -> DriverContext:
    events = [] if events is None else events
    return DriverContext(Bus(), structlog.get_logger(), lambda k, p=None: events.append((k, p)), plausible)


def test_bearing_spike_never_reaches_the_bus():
    """The probe's case: 124.99 °C 0.3 s after 30 °C was accepted and drove a 16 µm offset."""
    events = []
    c = ctx(events)
    assert c.bus.publish(Sample("temps", "t_front_bearing", 30.0, "°C", 100.0))
    assert not c.bus.publish(Sample("temps", "t_front_bearing", 124.99, "°C", 100.3))
    assert c.bus.latest[("temps", "t_front_bearing")].value == 30.0
    assert c.bus.plausible.status()["implausible"] == {"t_front_bearing": {"rate": 1}}
    (kind, payload), = events
    assert kind == "implausible_value" and payload["reason"] == "rate" and "t_front_bearing jumped" in payload["why"]
    # and the real temperature goes on being accepted
    assert c.bus.publish(Sample("temps", "t_front_bearing", 30.2, "°C", 106.3))


def test_nan_and_out_of_range_refused_for_any_unit():
    c = ctx()
    assert not c.bus.publish(Sample("m", "spindle_rpm", math.nan, "r/min", 1.0))
    assert not c.bus.publish(Sample("m", "spindle_rpm", 1e9, "r/min", 1.0))
    assert not c.bus.publish(Sample("m", "anything", math.inf, "", 1.0))
    assert c.bus.publish(Sample("m", "anything", 1e30, "", 1.0))       # no unit bounds: finite is enough
    assert c.bus.plausible.rejected["spindle_rpm"] == {"not_finite": 1, "out_of_range": 1}
    assert c.bus.published == 1


@pytest.mark.parametrize("bad", [math.nan, 2e6, -np.inf])
def test_a_device_channels_bad_sample_is_refused_and_the_others_pass(bad):
    # a device's channels conditioned together carry their extremes to the gate: one channel's
    # NaN, or a sample beyond 100 000 g, refuses its block alone
    from lathed.analysis.conditioning import Conditioner, ConditionerBank
    c = ctx()
    bank = ConditionerBank()
    for k in range(3):
        bank.join(k, Conditioner(51200, 1.0, 2.0), k)
    data = np.random.default_rng(5).normal(0.0, 10.0, (1024, 3)).astype(np.float32)
    data[500, 1] = bad
    for k in range(3):
        _, _, y, (rows, row) = bank.take(k, data)
        assert c.bus.publish(Block(f"accel{k}", "acceleration", 51200.0, 1.0, 0, y, None, rows, row)) == (k != 1)
    reason = "not_finite" if math.isnan(bad) or math.isinf(bad) else "out_of_range"
    assert c.bus.plausible.rejected == {"acceleration": {reason: 1}}
    # and the next block passes on every channel: the bad sample left nothing in the filters
    data = np.random.default_rng(6).normal(0.0, 10.0, (1024, 3)).astype(np.float32)
    for k in range(3):
        _, _, y, (rows, row) = bank.take(k, data)
        assert c.bus.publish(Block(f"accel{k}", "acceleration", 51200.0, 1.0, 1024, y, None, rows, row))
    assert c.bus.plausible.rejected == {"acceleration": {reason: 1}}


def test_without_a_rate_bound_two_values_at_one_instant_are_accepted():
    # an MTConnect agent reports a load that rose and fell within its timestamp's resolution:
    # no rate bound (%) times 0 s was NaN, and the second value was refused as a jump
    p = Plausibility()
    assert p.check("spindle_load_pct", "%", 40.0, 5.0) is None
    assert p.check("spindle_load_pct", "%", 12.5, 5.0) is None
    assert p.check("t_motor", "°C", 20.0, 5.0) is None
    assert p.check("t_motor", "°C", 20.4, 5.0) is None               # within tol at 0 s
    assert p.check("t_motor", "°C", 30.0, 5.0) is not None           # a rate bound still holds


def test_after_a_long_gap_a_value_within_range_is_accepted():
    p = Plausibility()
    assert p.check("t_motor", "°C", 20.0, 0.0) is None
    assert p.check("t_motor", "°C", 60.0, 5.0) is not None          # 8 °C/s: not heat
    assert p.check("t_motor", "°C", 60.0, 600.0) is None            # 10 min later: plausible


def test_after_a_reconnect_the_time_unwatched_vouches_for_nothing():
    """Issue 35 case 1: the board's link dropped; after the reconnect any value the gap's
    length allowed was taken (another board on the port, 10 °C colder). Now the first value
    back must lie within tol of the last; a new level is taken once confirmed (a rebase)."""
    p = Plausibility(confirm=3)
    assert p.check("t_motor", "°C", 32.0, 0.0) is None
    p.link_lost()
    assert p.check("t_motor", "°C", 22.0, 35.0)[0] == "rate"          # 35 s later: was accepted
    assert p.check("t_motor", "°C", 22.0, 41.0)[0] == "rate"
    assert p.check("t_motor", "°C", 22.0, 47.0) is None              # three alike: a real level
    assert p.rebased["t_motor"] == 1
    assert p.check("t_motor", "°C", 22.1, 53.0) is None              # watched again: the rate holds
    p.link_lost()
    assert p.check("t_motor", "°C", 22.4, 600.0) is None             # within tol: taken at once
    # a sensor forgotten (off its wire) and back is judged against its last value the same way
    p.forget("t_motor")
    assert p.check("t_motor", "°C", 40.0, 1200.0)[0] == "rate"


def test_a_real_jump_is_confirmed_by_consistent_readings_a_spike_never():
    p = Plausibility(confirm=3)
    assert p.check("t", "°C", 20.0, 0.0) is None
    # one spike, then back: the spike is refused, the way back is accepted
    assert p.check("t", "°C", 90.0, 1.0)[0] == "rate"
    assert p.check("t", "°C", 20.1, 2.0) is None
    # a new level held for three readings (the first accepted value was the wrong one)
    assert p.check("t", "°C", 70.0, 3.0)[0] == "rate"
    assert p.check("t", "°C", 70.1, 4.0)[0] == "rate"
    assert p.check("t", "°C", 70.0, 5.0) is None
    assert p.rebased["t"] == 1
    assert p.check("t", "°C", 70.2, 6.0) is None


def test_reports_are_rate_limited_but_every_rejection_counted():
    events = []
    c = ctx(events)
    for i in range(50):
        c.bus.publish(Sample("m", "spindle_rpm", math.nan, "r/min", float(i)))
    assert len(events) == 1 and c.bus.plausible.rejected["spindle_rpm"]["not_finite"] == 50


def test_bounds_from_config_exact_name_glob_and_unit_default():
    sec = Section("t.toml", "sensor.temps.plausible", {
        "confirm": 2, "t_front_bearing": {"min": 10.0, "max": 90.0}, "t_*": {"rate": 0.5}})
    p = Plausibility.from_section(sec)
    b = p.bounds("t_front_bearing", "°C")
    assert (b.lo, b.hi, b.rate) == (10.0, 90.0, 2.0)           # rate from the unit's default
    b = p.bounds("t_room", "°C")
    assert (b.lo, b.hi, b.rate) == (-55.0, 150.0, 0.5)
    assert p.confirm == 2
    with pytest.raises(ConfigError, match=r"\[sensor.temps.plausible.t_x\] min: 5 is above max 1"):
        Plausibility.from_section(Section("t.toml", "sensor.temps.plausible", {"t_x": {"min": 5, "max": 1}}))
    with pytest.raises(ConfigError, match=r"\[sensor.temps.plausible.t_x\] rte: unknown key"):
        Plausibility.from_section(Section("t.toml", "sensor.temps.plausible", {"t_x": {"rte": 5}}))


def test_driver_reads_its_plausible_table():
    d = DS18B20Serial("temps", Section("t.toml", "sensor.temps", {
        "port": "/dev/null", "plausible": {"t_*": {"max": 40.0}}}))
    d.ctx = ctx(plausible=d.plausible)
    assert d.handle_line(format_temperature_line(0, 0, {"room": 20.0, "front": 45.0}), 1.0) == 1
    assert d.ctx.bus.plausible.rejected == {"t_front": {"out_of_range": 1}}
    assert "front" not in d.status()["sensors"]


REGS = {"spindle_rpm_cmd": {"address": 0, "type": "float32", "writable": True},
        "spindle_rpm": {"address": 2, "type": "float32", "unit": "r/min"}}
IDENT = {"identification": {"serial_number": "L-1"}, "identity": {"serial_number": {"address": 40, "words": 8}}}
NAN32 = [0x7FC0, 0x0000]
RPM_1000 = [0x447A, 0x0000]


class FakeRead:
    def __init__(self, registers):
        self.registers = registers

    def isError(self):
        return False


class FakeClient:
    def __init__(self, registers):
        self.regs = registers

    async def read_holding_registers(self, start, count, device_id):
        return FakeRead(self.regs[start:start + count])


def test_modbus_float32_nan_reaches_neither_model_nor_guard_reference():
    d = ModbusCNC("lathe", Section("t.toml", "machine.lathe", {"host": "h", "registers": REGS, **IDENT}))
    d.ctx = ctx()
    d.model.link_up()
    d.client = FakeClient(RPM_1000 + RPM_1000)
    asyncio.run(d._read_group(d.groups[min(d.groups)]))
    assert d.current("spindle_rpm") == 1000.0
    d.client = FakeClient(NAN32 + NAN32)
    asyncio.run(d._read_group(d.groups[min(d.groups)]))
    # the last good value is kept (it goes stale in time); NaN never becomes it
    assert d.current("spindle_rpm") == 1000.0
    assert d.model.live("spindle_rpm") == 1000.0
    assert d.ctx.bus.latest[("lathe", "spindle_rpm")].value == 1000.0
    assert d.ctx.bus.plausible.rejected == {"spindle_rpm_cmd": {"not_finite": 1},
                                             "spindle_rpm": {"not_finite": 1}}


def test_blocks_checked_for_rate_rpm_and_samples():
    c = ctx()
    x = np.zeros(64)
    assert c.bus.publish(Block("accel", "acceleration", 51200.0, 1.0, 0, x, 3000.0))
    assert not c.bus.publish(Block("accel", "acceleration", 51200.0, 1.0, 64, x, math.nan))
    assert not c.bus.publish(Block("accel", "acceleration", 0.0, 1.0, 64, x, 3000.0))
    bad = x.copy()
    bad[3] = math.inf
    assert not c.bus.publish(Block("accel", "acceleration", 51200.0, 1.0, 64, bad, 3000.0))
    assert c.bus.plausible.rejected == {"acceleration": {"rpm": 1, "rate": 1, "not_finite": 1}}


class FakeStore:
    def __init__(self):
        self.records = []

    def record_future(self, kind, source, payload, t=None):
        import concurrent.futures
        self.records.append((kind, source, payload))
        f = concurrent.futures.Future()
        f.set_result(None)
        return f


def test_supervisor_gates_every_driver_and_status_shows_the_refusals(capsys):
    from lathed.config import Instance
    from lathed.cli.main import _print_implausible
    from lathed.supervisor import Plan, Supervisor
    sec = Section("t.toml", "sensor.temps", {"port": "/dev/null"})
    d = DS18B20Serial("temps", sec)
    inst = Instance("sensor", "temps", "ds18b20_serial", sec, Section("t.toml", "sensor.temps", {}))
    store = FakeStore()
    sup = Supervisor(None, Plan(drivers={"temps": (inst, d)}), Bus(), store, lambda *a: None)
    d.handle_line(format_temperature_line(0, 0, {"front_bearing": 30.0}), 100.0)
    d.handle_line(format_temperature_line(1, 300, {"front_bearing": 124.99}), 100.3)
    (entry,) = sup.status()["sensors"]
    assert entry["implausible"] == {"t_front_bearing": {"rate": 1}}
    assert entry["last_value"] == {"t_front_bearing": 30.0}
    assert [(k, s) for k, s, _ in store.records] == [("implausible_value", "temps")]
    capsys.readouterr()       # the warning logged
    _print_implausible(entry)
    assert capsys.readouterr().out == "    implausible values refused: t_front_bearing rate 1\n"
