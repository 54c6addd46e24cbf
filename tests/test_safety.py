"""The safety guard refuses, never clamps; every refusal says why."""
from __future__ import annotations

import math

import pytest
from hypothesis import given, strategies as st

from lathed.command import Command
from lathed.config import ConfigError, Section
from lathed.safety import Limits, SafetyGuard


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def guard(**kw):
    clock = Clock()
    lim = Limits(rpm_min=300, rpm_max=6000, rpm_step_max=2000, rpm_rate_max=1000, offset_max_um=50,
                 offset_rate_max_um_s=5, **kw)
    return SafetyGuard({"lathe": lim}, clock=clock), clock


def cmd(action, value, machine="lathe"):
    return Command(machine, action, value, source="test")


def test_within_limits_passes():
    g, _ = guard()
    assert g.check(cmd("spindle_rpm", 1500), current=1000) is None


@pytest.mark.parametrize("value, why", [
    (6500, "spindle speed 6500 r/min outside [300, 6000]"),
    (100, "spindle speed 100 r/min outside [300, 6000]"),
    (float("nan"), "spindle_rpm value nan is not a finite number"),
    (float("inf"), "spindle_rpm value inf is not a finite number"),
    (True, "spindle_rpm value True is not a finite number"),
    ("1500", "spindle_rpm value '1500' is not a finite number"),
])
def test_out_of_range_or_not_a_number(value, why):
    g, _ = guard()
    assert g.check(cmd("spindle_rpm", value), current=1500) == why


def test_step_bound():
    g, _ = guard()
    assert g.check(cmd("spindle_rpm", 4000), current=1500) == "spindle speed step 2500 r/min exceeds 2000"


def test_a_release_is_bounded_by_the_range_only():
    # back to the program's own speed: the way back may be a bigger step, and come sooner,
    # than the steps that led away; refused, lathed's override would hold over the next parts
    from dataclasses import replace
    g, clock = guard()
    c = cmd("spindle_rpm", 3400)
    g.passed(c)
    back = replace(cmd("spindle_rpm", 1000), release=True)
    assert g.check(replace(back, release=False), current=3400).startswith("spindle speed step 2400")
    assert g.check(back, current=3400) is None
    assert g.check(replace(back, value=7000.0), current=3400) == "spindle speed 7000 r/min outside [300, 6000]"


def test_an_interlock_refuses_every_command_a_release_too():
    # a thread being cut: no speed, no offset, not even the way back, may change under it
    from dataclasses import replace
    g, _ = guard()
    why = "machine lathe is cutting a thread (threading = 1)"
    assert g.check(cmd("spindle_rpm", 1500), current=1000, interlock=why) == why
    assert g.check(replace(cmd("spindle_rpm", 1000), release=True), current=1500, interlock=why) == why
    assert g.check(cmd("offset_x_um", 2.0), current=0.0, interlock=why) == why
    assert g.check(cmd("spindle_rpm", 1500), current=1000, interlock=None) is None


def test_rate_bound_between_commands():
    g, clock = guard()
    c = cmd("spindle_rpm", 1500)
    assert g.check(c, current=1500) is None
    g.passed(c)
    clock.t = 0.5
    assert g.check(cmd("spindle_rpm", 2500), current=1500).startswith("spindle_rpm changing at 2e+03 r/min per s")
    clock.t = 1.0
    assert g.check(cmd("spindle_rpm", 2500), current=1500) is None


def test_offsets_bounded_and_phased_in():
    g, clock = guard()
    assert g.check(cmd("offset_x_um", 60)) == "offset 60 µm beyond ±50 µm"
    g.passed(cmd("offset_x_um", 0))
    clock.t = 1.0
    assert g.check(cmd("offset_x_um", 10)).startswith("offset_x_um changing at 10 µm/s")
    assert g.check(cmd("offset_x_um", 5)) is None


def test_an_offset_step_is_bounded_from_the_machines_present_offset():
    # the first command after a start has no pace reference (nothing sent yet): a jump
    # from the offset the control holds is refused all the same
    g, _ = guard(offset_step_max_um=10)
    assert g.check(cmd("offset_x_um", 45), current=-4.67) == "offset step 49.67 µm exceeds 10"
    assert g.check(cmd("offset_x_um", 3), current=-4.67) is None
    assert g.check(cmd("offset_x_um", 45)) is None          # no present value known: the range only


def test_unknown_machine_and_action():
    g, _ = guard()
    assert g.check(cmd("spindle_rpm", 1000, machine="mill")) == "no limits configured for machine 'mill'"
    assert g.check(cmd("coolant", 1)) == "unknown action 'coolant'"


def test_commands_refused_when_not_configured():
    g = SafetyGuard({"lathe": Limits()})
    assert "not allowed" in g.check(cmd("spindle_rpm", 1000))
    assert "not allowed" in g.check(cmd("offset_x_um", 1))


@given(st.floats(allow_nan=True, allow_infinity=True), st.floats(min_value=0, max_value=10_000))
def test_nothing_outside_limits_ever_passes(value, current):
    """Whatever an analysis computes, no value outside the limits reaches a machine."""
    g, _ = guard()
    if g.check(cmd("spindle_rpm", value), current=current) is None:
        assert math.isfinite(value) and 300 <= value <= 6000 and abs(value - current) <= 2000


@pytest.mark.parametrize("current", [math.nan, math.inf, -math.inf])
def test_non_finite_reference_refused(current):
    """issue 18 D6: abs(v - nan) > step is False, so a NaN present value let any step through."""
    g, _ = guard()
    why = g.check(cmd("spindle_rpm", 6000.0), current=current)
    assert why is not None and "not a finite number" in why and "present value" in why


@given(st.floats(allow_nan=True, allow_infinity=True), st.floats(allow_nan=True, allow_infinity=True))
def test_nothing_passes_against_any_reference(value, current):
    g, _ = guard()
    if g.check(cmd("spindle_rpm", value), current=current) is None:
        assert math.isfinite(current) and abs(value - current) <= 2000


def test_limits_from_config():
    lim = Limits.from_section(Section("f", "machine.l.limits", {"spindle_rpm_max": 4000.0,
                                                                "spindle_rpm_min": 100.0}))
    assert lim.rpm_max == 4000 and lim.rpm_min == 100
    with pytest.raises(ConfigError, match="spindle_rpm_min: 5000 is above spindle_rpm_max 4000"):
        Limits.from_section(Section("f", "machine.l.limits", {"spindle_rpm_max": 4000.0,
                                                              "spindle_rpm_min": 5000.0}))
