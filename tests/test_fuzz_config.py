"""Property: any TOML text gives a validated config or a ConfigError of one
line per problem, never another exception (issue 13 item 9, issue 18)."""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lathed.config import CATEGORIES, ConfigError
from lathed.daemon import prepare

KEYS = ["plugin", "host", "port", "poll", "input", "machine", "chatter", "thermal", "registers", "limits",
        "retry_initial", "retry_max", "enabled", "device", "baudrate", "stale_after", "kind", "transport",
        "spindle_rpm_max", "spindle_rpm_min", "offset_max_um", "address", "type", "writable", "mode",
        "strategy", "modes", "detector", "tool", "material", "dsn", "name", "state_dir", "runtime_dir",
        "plugin_dirs", "log_level", "keep_days", "prune_every", "serial_link", "time_scale", "x",
        "tls", "ca_file", "cert_file", "key_file", "username", "password", "live", "cell", "batch"]
PLUGINS = ["modbus_cnc", "ds18b20_serial", "vibration_tcp", "records", "postgres_sink", "can_robot", "chatter",
           "suppression", "thermal", "mqtt_sink", "nope"]

scalars = st.one_of(
    st.booleans(), st.integers(min_value=-(2 ** 63), max_value=2 ** 63 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(PLUGINS),
    st.sampled_from(["100ms", "6s", "-1s", "2min", "fast", "", "127.0.0.1", "{runtime_dir}/x", "float32"]),
    st.text(max_size=12))
values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.sampled_from(KEYS), inner, max_size=5)), max_leaves=12)
tables = st.dictionaries(st.sampled_from(KEYS), values, max_size=8)
instances = st.dictionaries(st.sampled_from(["lathe", "temps", "accel", "chatter", "a", "1bad", "x-y"]),
                            tables, max_size=3)
documents = st.fixed_dictionaries({}, optional={
    "daemon": tables, "store": tables, "simulator": tables,
    **{c: instances for c in CATEGORIES}, "other": tables})


def outcome(text: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "lathed.toml"
        path.write_text(text)
        try:
            prepare(path, strict=True)
        except ConfigError as e:
            lines = str(e).splitlines()
            assert lines and all(ln.strip() for ln in lines), repr(str(e))
            assert not any("Traceback" in ln for ln in lines)


# drawing a nested document costs hypothesis more than loading it: 100 a run, fresh ones every run
@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(documents)
def test_any_structured_config_is_valid_or_one_line_per_problem(doc):
    try:
        text = tomli_w.dumps(doc)
    except (TypeError, ValueError):
        return                               # not representable in TOML: nothing to load
    outcome(text)


@settings(max_examples=150, deadline=None)
@given(st.text(alphabet=st.sampled_from(list("[]=\"'.\n #abcdelmnprst0123456789{}-_,")), max_size=120))
def test_any_text_is_valid_or_one_line_per_problem(text):
    outcome(text)


def test_non_finite_and_huge_values_are_refused_in_one_line():
    doc = {"machine": {"lathe": {"plugin": "modbus_cnc", "host": "h", "port": 2 ** 63 - 1,
                                 "registers": {"spindle_rpm": {"address": math.inf, "type": "float32"}}}}}
    outcome(tomli_w.dumps(doc))
