"""The safety guard refuses, never clamps; every refusal says why."""
from __future__ import annotations

import math

import numpy as np
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
    lim = Limits(**{"rpm_min": 300, "rpm_max": 6000, "rpm_step_max": 2000, "rpm_rate_max": 1000,
                    "offset_max_um": 50, "offset_rate_max_um_s": 5, **kw})
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


def test_a_release_is_the_programs_own_value_bounded_by_the_range_only():
    # back to the program's own speed (as the driver reads it): the way back may be a bigger
    # step, and come sooner, than the steps that led away; refused, lathed's override would
    # hold over the next parts
    g, clock = guard()
    g.passed(cmd("spindle_rpm", 3400))
    back = cmd("spindle_rpm", 1000)
    assert g.check(back, current=3400).startswith("spindle speed step 2400")
    assert g.check(back, current=3400, program=1000.0) is None
    assert g.check(back, current=3400, program=1000.3) is None       # two registers' rounding
    assert g.check(cmd("spindle_rpm", 7000.0), current=3400, program=7000.0) == \
        "spindle speed 7000 r/min outside [300, 6000]"


# issue 35 case 2: a plugin's Command(release=True) skipped the step and pace bounds; the
# caller's claim (that flag, where the class still has one) buys nothing now
CLAIM = {"release": True} if "release" in Command.__dataclass_fields__ else {}


def test_a_release_claimed_by_the_caller_is_bounded_as_any_command():
    """Releases of 6000 then 300 r/min 1 s apart swung the lathe 2000 -> 6000 -> 300 against a
    step bound of 3000: the value is judged against what the machine runs, not the flag."""
    g, clock = guard(rpm_step_max=3000)
    g.passed(cmd("spindle_rpm", 2000))
    clock.t = 1.0
    up = Command("lathe", "spindle_rpm", 6000.0, source="plugin", **CLAIM)
    assert g.check(up, current=2000, program=2000.0) == "spindle speed step 4000 r/min exceeds 3000"
    down = Command("lathe", "spindle_rpm", 300.0, source="plugin", **CLAIM)
    assert g.check(down, current=2000, program=2000.0).startswith("spindle_rpm changing at 1.7e+03 r/min per s")


def test_a_step_is_refused_when_the_machines_present_value_is_not_known():
    # issue 35 case 15: a stale reading and nothing sent yet: the range alone was checked
    g, _ = guard(offset_step_max_um=10)
    why = g.check(cmd("offset_x_um", 45))
    assert why == ("offset_x_um: the machine's present value is not known (not read lately), so the step "
                   "to 45 cannot be bounded (offset_step_max_um 10)")
    assert g.check(cmd("spindle_rpm", 5900)).startswith("spindle_rpm: the machine's present value is not known")
    # and not from the last command sent either: the machine may have moved since
    g.passed(cmd("spindle_rpm", 5900))
    assert g.check(cmd("spindle_rpm", 5900)).startswith("spindle_rpm: the machine's present value is not known")
    # without a step bound there is nothing to take from it
    g2 = SafetyGuard({"lathe": Limits(rpm_min=300, rpm_max=6000)})
    assert g2.check(cmd("spindle_rpm", 5900)) is None


@pytest.mark.parametrize("value", [np.float32(1500.0), np.int64(1500), np.float64(1500.0), 1500])
def test_numpy_and_int_values_are_numbers(value):
    # issue 35 case 11: a float32 from a numeric core was refused as "not a finite number"
    g, _ = guard()
    assert g.check(cmd("spindle_rpm", value), current=1500) is None


def test_an_int_beyond_a_float_is_refused_not_raised():
    g, _ = guard()
    assert g.check(cmd("spindle_rpm", 10**400), current=1500).startswith("spindle_rpm value 1000000")
    assert g.check(cmd("spindle_rpm", np.bool_(True)), current=1500).endswith("is not a finite number")


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
    assert g.check(cmd("offset_x_um", 60), current=0.0) == "offset 60 µm beyond ±50 µm"
    g.passed(cmd("offset_x_um", 0))
    clock.t = 1.0
    assert g.check(cmd("offset_x_um", 10), current=0.0).startswith("offset_x_um changing at 10 µm/s")
    assert g.check(cmd("offset_x_um", 5), current=0.0) is None


def test_an_offset_step_is_bounded_from_the_machines_present_offset():
    # the first command after a start has no pace reference (nothing sent yet): a jump
    # from the offset the control holds is refused all the same
    g, _ = guard(offset_step_max_um=10)
    assert g.check(cmd("offset_x_um", 45), current=-4.67) == "offset step 49.67 µm exceeds 10"
    assert g.check(cmd("offset_x_um", 3), current=-4.67) is None


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
