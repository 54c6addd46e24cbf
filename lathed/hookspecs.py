"""Every hook a lathed plugin can implement, in one place.

Hooks are synchronous and return objects (classes or factories); any I/O
lives in the methods of those objects, which the supervisor runs on the event
loop. A plugin is a module (installed under the ``lathed.plugins`` entry-point
group, or a ``.py`` file in a drop-in directory named by ``[daemon]
plugin_dirs``) that defines functions with these names, decorated with
``lathed.hookimpl``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import pluggy

if TYPE_CHECKING:
    from lathed.analyzer import Analyzer
    from lathed.driver import Driver

hookspec = pluggy.HookspecMarker("lathed")
hookimpl = pluggy.HookimplMarker("lathed")


@hookspec
def lathed_driver_types() -> dict[str, type[Driver]]:
    """Driver classes this plugin provides, by the name a config table uses
    in its ``plugin`` key (``[machine.X]`` or ``[sensor.X]``).

    A driver talks to one machine or sensor: it publishes samples on the bus
    and carries out commands the safety guard has passed. It never decides.
    """


@hookspec
def lathed_analyzer_types() -> dict[str, type[Analyzer]]:
    """Analyzer classes by the name an ``[analyzer.X]`` table uses in its
    ``plugin`` key. Analyzers read the bus, decide, and ask for commands;
    they never talk to hardware."""


@hookspec
def lathed_chatter_detectors() -> dict[str, Any]:
    """Extra chatter detectors by name: each value is a subclass of
    :class:`lathed.analysis.chatter.base.RevolutionDetector`, built as ``cls(rate_hz, **params)``;
    it overrides what it changes. Built-in detectors need no hook."""


@hookspec
def lathed_thermal_candidates() -> list[Any]:
    """Extra candidate effects for the thermal residual loop, each a subclass of
    :class:`lathed.analysis.thermal.Candidate`."""


@hookspec
def lathed_event_kinds() -> list[str]:
    """Kinds of event this plugin's drivers and analyzers record beyond lathed's own
    (``lathed.schema.KINDS``): ``lathectl events --kind`` and event subscriptions take
    them before the first is recorded, and refuse a misspelt one."""
