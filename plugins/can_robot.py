"""A robot arm over CAN (python-can), frames decoded from a DBC file with cantools.

Signals are found by name in whichever frame carries them (``j1_deg``..``j6_deg``,
``tool_x_mm``.., ``state``, ``gripper``, ``alarm_code``, ``cycle_count``, ``program``); a
frame's ``counter`` signal counts lost frames. Unknown ids are counted and ignored, frames
that do not decode counted as malformed. Keys: docs/configuration.md; the shipped DBC's
layout: docs/machines.md.
"""
from __future__ import annotations

import asyncio
import re
import time
from collections import Counter
from pathlib import Path

from lathed import hookimpl
from lathed.bus import Sample
from lathed.config import Section
from lathed.driver import Driver
from lathed.machine import MachineModel

REQUIRED = ("j1_deg", "j2_deg", "j3_deg", "j4_deg", "j5_deg", "j6_deg", "tool_x_mm", "tool_y_mm", "tool_z_mm",
            "state", "gripper", "alarm_code", "cycle_count")
GRIPPER = {0: "open", 1: "closed", 2: "moving"}
BATCH_S = 0.05    # frames are read in a worker thread in batches this long: one loop hop per batch

# python-can and cantools, imported with the first robot arm configured: the daemon loads every
# plugin at start, and a quarter second of import per start is not for daemons without one
can = cantools = None


def _import_can() -> None:
    global can, cantools
    import can
    import cantools


class ReadAhead:
    """A pyserial port whose ``read`` takes everything waiting in one system call.

    python-can's slcan reader asks its port for one byte at a time (a select
    and a read per byte: ~25 of each per frame, in a worker thread); handed
    this wrapper, those bytes come from memory. Everything else is the port's."""

    def __init__(self, port) -> None:
        object.__setattr__(self, "_port", port)
        object.__setattr__(self, "_buf", bytearray())

    def read(self, size: int = 1) -> bytes:
        if len(self._buf) < size:
            # blocks as the port does for the bytes asked (its timeout), and takes what came with them
            self._buf += self._port.read(max(size - len(self._buf), self._port.in_waiting))
        out = bytes(self._buf[:size])
        del self._buf[:size]
        return out

    @property
    def in_waiting(self) -> int:
        return len(self._buf) + self._port.in_waiting

    def reset_input_buffer(self) -> None:
        self._buf.clear()
        self._port.reset_input_buffer()

    def __getattr__(self, name: str):
        return getattr(self._port, name)

    def __setattr__(self, name: str, value) -> None:
        setattr(self._port, name, value)


class CanRobot(Driver):
    role = "machine"
    kind = "robot_arm"

    def __init__(self, name: str, section: Section):
        super().__init__(name, section)
        _import_can()
        self.interface = section.getstr("interface", choices=tuple(sorted(can.VALID_INTERFACES)))
        self.channel = section.getstr("channel")
        self.bitrate = section.getint("bitrate", 0, minval=0, maxval=8_000_000) or None
        dbc = Path(section.getstr("dbc", "robot_arm.dbc"))
        self.dbc_path = dbc if dbc.is_absolute() else Path(section.file).parent / dbc
        self.timeout = section.getduration("timeout", 1.0, minval=0.05, maxval=600)
        self.stale_after = section.getduration("stale_after", 1.0, minval=0.05, maxval=3600)
        try:
            self.db = cantools.database.load_file(str(self.dbc_path))
        except OSError as e:
            raise section.error("dbc", f"cannot load {self.dbc_path}: {str(e).splitlines()[0]}") from None
        except (ValueError, cantools.database.UnsupportedDatabaseFormatError) as e:
            # ValueError: cantools goes by the name's extension and knows no such format (a .json),
            # which came out as "failed to start" with a path inside cantools
            raise section.error("dbc", f"{self.dbc_path} is not a DBC file ({str(e).splitlines()[0]})") from None
        # cantools keeps the last of two messages on one frame id (a warning on stderr only):
        # the first's signals would never be decoded
        ids = [int(i) for i in re.findall(r"^\s*BO_\s+(\d+)\s", self.dbc_path.read_text(errors="replace"), re.M)]
        twice = sorted({i for i in ids if ids.count(i) > 1})
        if twice:
            raise section.error("dbc", f"{self.dbc_path} defines frame id {twice[0]} (0x{twice[0]:X}) twice")
        have = {s.name for m in self.db.messages for s in m.signals}
        missing = [s for s in REQUIRED if s not in have]
        if missing:
            raise section.error("dbc", f"{self.dbc_path} lacks signal(s) {', '.join(missing)}; "
                                       f"a robot arm needs: {', '.join(REQUIRED)}")
        self.frame_ids = {m.frame_id for m in self.db.messages}
        self.bus: can.BusABC | None = None
        self.model = MachineModel(self.kind, self.stale_after, self._record)
        self.frames = 0
        self.counts: Counter = Counter()      # malformed, unknown_id, lost_frames
        self._counters: dict[int, int] = {}
        self._cycles: int | None = None       # cycle_count unwrapped past 16 bits
        self._last_frame = 0.0
        self._cycle_t: float | None = None    # when cycle_count last stepped by one

    def _record(self, kind: str, payload: dict) -> None:
        if self.ctx is not None:
            self.ctx.record(kind, payload)

    # -- link ---------------------------------------------------------------
    def _open(self) -> can.BusABC:
        kw = {"interface": self.interface, "channel": self.channel}
        if self.bitrate:
            kw["bitrate"] = self.bitrate
        if self.interface == "slcan":
            kw["sleep_after_open"] = 0   # a pty or CANable answers at once
            # python-can's default 1 ms serial timeout makes its reader spin a
            # thousand times a second while the bus is quiet; a byte still
            # returns the moment it arrives
            kw["timeout"] = 0.05
        bus = can.Bus(**kw)
        if self.interface == "slcan" and hasattr(bus, "serialPortOrig"):   # python-can 4.x's name for its port
            bus.serialPortOrig = ReadAhead(bus.serialPortOrig)
        return bus

    async def connect(self) -> None:
        try:
            self.bus = await asyncio.to_thread(self._open)
        except (can.CanError, OSError, ValueError) as e:
            raise ConnectionError(f"cannot open CAN {self.interface} {self.channel}: {e} "
                                  "(adapter unplugged?)") from None
        self._counters.clear()   # the controller may have restarted: counters start over
        deadline = time.monotonic() + self.timeout
        # a CAN bus with no traffic looks exactly like an unplugged one: the link
        # counts as up only once the robot is heard
        while not self._handle(await asyncio.to_thread(self._recv_batch)):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no frames from the robot on {self.interface} {self.channel} for "
                                   f"{self.timeout:g} s (controller off, bus unterminated or wrong bitrate?)")
        self.model.link_up()

    async def close(self) -> None:
        self.model.link_down()
        if self.bus is not None:
            bus, self.bus = self.bus, None
            try:
                await asyncio.to_thread(bus.shutdown)
            except Exception as e:   # the adapter is usually already gone when we get here
                if self.ctx is not None:
                    self.ctx.log.debug("can_shutdown_failed", error=str(e))

    def _recv_batch(self) -> list[can.Message]:
        out: list[can.Message] = []
        end = time.monotonic() + BATCH_S
        while (left := end - time.monotonic()) > 0:
            try:
                msg = self.bus.recv(left)
            except can.CanOperationError as e:
                if out:
                    return out   # hand over what arrived; the next read raises again
                raise ConnectionError(f"CAN {self.interface} {self.channel} lost: {e} (adapter unplugged?)")
            except (ValueError, IndexError):
                self.counts["malformed"] += 1   # garbage the adapter could not parse
                continue
            if msg is None:
                break
            out.append(msg)
        return out

    # -- decoding -----------------------------------------------------------
    def _handle(self, msgs: list[can.Message]) -> int:
        """Decode frames into the model; returns how many were valid."""
        good = 0
        for msg in msgs:
            if msg.is_error_frame or msg.is_remote_frame:
                continue
            if msg.arbitration_id not in self.frame_ids:
                self.counts["unknown_id"] += 1
                continue
            try:
                sig = self.db.decode_message(msg.arbitration_id, bytes(msg.data), decode_choices=False)
            except Exception:   # cantools raises several types for a short or bad frame
                self.counts["malformed"] += 1
                continue
            good += 1
            self._apply(msg.arbitration_id, sig, time.time())
        if good:
            self.frames += good
            self._last_frame = time.monotonic()
            self.mark_data()
        return good

    def _apply(self, fid: int, sig: dict, t: float) -> None:
        m = self.model
        if "counter" in sig:
            c, last = int(sig["counter"]), self._counters.get(fid)
            if last is not None and c != (last + 1) % 256:
                self.counts["lost_frames"] += (c - last - 1) % 256
            self._counters[fid] = c
        for name, v in sig.items():
            if name == "counter":
                continue
            v = float(v)
            if name.startswith("j") and name.endswith("_deg"):
                m.set_axis(name[:-4], v, t)
            elif name.startswith("tool_") and name.endswith("_mm"):
                m.set_axis(name[:-3], v, t)
            elif name == "state":
                m.set_running(int(v) == 1, t)
            elif name == "gripper":
                m.set("gripper", GRIPPER.get(int(v), f"code {int(v)}"), t)
            elif name == "alarm_code":
                m.set_alarms([int(v)] if int(v) else [], t)
            elif name == "cycle_count":
                last, count = self._cycles, self._unwrap(int(v))
                if last is not None and count == last + 1:
                    # the arm reports no cycle time: the time between two counts is one
                    if self._cycle_t is not None:
                        m.set("cycle_time_s", t - self._cycle_t, t)
                    self._cycle_t = t
                elif count != last:
                    self._cycle_t = None   # a jump or a restart: the next full cycle tells
                m.set("part_count", count, t)
            elif name == "program":
                m.set("program", int(v), t)
            self.ctx.bus.publish(Sample(self.name, name, v, "", t))

    def _unwrap(self, raw: int) -> int:
        if self._cycles is None:
            self._cycles = raw
        else:
            step = (raw - self._cycles) % 65536
            # a small step forward is progress; anything else is a controller restart
            self._cycles = self._cycles + step if step < 32768 else raw
        return self._cycles

    async def run(self) -> None:
        while True:
            self._handle(await asyncio.to_thread(self._recv_batch))
            if time.monotonic() - self._last_frame > self.timeout:
                raise TimeoutError(f"robot silent on {self.interface} {self.channel} for {self.timeout:g} s "
                                   "(controller off or CAN cable pulled?)")

    def quantities(self) -> frozenset[str]:
        return frozenset(s.name for m in self.db.messages for s in m.signals) - {"counter"}

    def current(self, action: str) -> float | None:
        return None

    def status(self) -> dict:
        return {"spindle_rpm": None, "machine_state": self.model.state(), "model": self.model.snapshot(),
                "link": {"interface": self.interface, "channel": self.channel, "frames": self.frames,
                         "errors": dict(self.counts)}}


@hookimpl
def lathed_driver_types():
    return {"can_robot": CanRobot}
