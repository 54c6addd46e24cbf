"""Suppression's strategies as classes (issue 42 item 4): each reads its own keys, a key of
another strategy is refused, and the variation strategy's modulation runs and stops with
the cut."""
from __future__ import annotations

import asyncio
import time

import pytest

from lathed.bus import Sample
from lathed.config import ConfigError, Section
from lathed_plugins.suppression import SuppressionAnalyzer
from lathed_plugins.suppression_strategies import STRATEGIES, Strategy
from tests.test_stability_adopt import Harness
from tests.test_suppression_hold import _cut

BASE = {"chatter": "chatter", "machine": "lathe"}


def _read(cls, **data) -> set[str]:
    section = Section("t.toml", "analyzer.suppress", {**BASE, **data})
    cls(section)
    return section._read


def test_each_strategy_reads_its_own_keys_beside_the_shared_ones():
    shared = _read(Strategy)
    assert {"max_rpm", "min_rpm", "settle_revs", "max_speed_ratio", "avoid"} <= shared
    for name, cls in STRATEGIES.items():
        assert cls.name == name
        assert _read(cls) - shared == set(cls.keys), name


@pytest.mark.parametrize("strategy, key, value, owners", [
    ("lobes", "ssv_amplitude", 0.2, "variation"),
    ("frequency", "when_no_stable_speed", "hold", "lobes"),
    ("variation", "rated_rpm", 750.0, "lobes | frequency | rated"),
])
def test_a_key_of_another_strategy_is_refused_naming_the_strategies_that_read_it(strategy, key, value, owners):
    data = {**BASE, "strategy": strategy, key: value}
    with pytest.raises(ConfigError) as e:
        SuppressionAnalyzer("suppress", Section("t.toml", "analyzer.suppress", data))
    assert str(e.value) == (f"t.toml: [analyzer.suppress] {key}: read only with strategy = {owners}; "
                            f"this table's strategy is {strategy!r}")


@pytest.fixture
def h(tmp_path):
    h = Harness(tmp_path, strategy="variation", max_speed_ratio=1.3, ssv_amplitude=0.1)
    h.start()
    yield h
    h.store.close()


async def _until(pred, what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.01)


def test_variation_modulates_the_speed_until_the_cut_ends(h):
    an = h.an

    async def main():
        await _cut(an, 1.3, alarms=1, leave=False)
        await _until(lambda: len(h.sent) >= 5, "the modulation's commands")
        task = an.strategy._task
        await an._on_machine(Sample("lathe", "depth_of_cut_mm", 0.0, "mm", time.time()))
        await an._on_chatter(Sample("chatter", "cutting", 0.0, "", time.time()))   # the cut ends (its state's owner)
        await asyncio.gather(task, return_exceptions=True)
        return task
    task = asyncio.run(main())
    assert task.cancelled() and an.strategy._task is None
    (act,) = h.events("suppression_action")
    assert act["strategy"] == "ssv" and act["sent"] is True and act["refused"] == "modulating"
    assert act["variation"]["kind"] == "sine" and act["variation"]["amplitude_ratio"] == 0.1
    speeds = [c.value for c in h.sent]
    assert speeds[0] == pytest.approx(2500.0)             # the sine starts at the mean speed
    assert all(2500.0 * 0.9 - 1e-6 <= n <= 2500.0 * 1.1 + 1e-6 for n in speeds)
    assert len({round(n, 3) for n in speeds}) > 2         # it moves
    assert {c.reason for c in h.sent} == {"speed variation (sine)"}


def test_a_refused_modulation_write_stops_the_modulation(h):
    an = h.an
    sent = h.sent

    async def command(cmd):
        sent.append(cmd)
        return {"sent": len(sent) < 3, "reason": None if len(sent) < 3 else "refused by the test"}
    an.ctx.command = command

    async def main():
        await _cut(an, 1.3, alarms=1, leave=False)
        await _until(lambda: an.strategy._task is not None and an.strategy._task.done(), "the modulation to stop")
        return an.strategy._task
    task = asyncio.run(main())
    assert not task.cancelled() and len(sent) == 3          # it stopped itself at the refusal
