"""``lathectl record``: a vibration sensor's samples to a WAV file, and beside it what an analyst needs.

    lathectl record SENSOR (--seconds S | --cuts N) [-o FILE.wav] [--pre S] [--post S] [--wait S]

The WAV holds the signal as the daemon's analyzers get it (32-bit float, in the sensor's
unit, at the device's rate; samples the stream lost are zeros there, and listed). The
sidecar FILE.json (lathed.analysis.recording.SIDECAR) holds the sensor's calibration and
device, the machine's speed over time, the cut state, the live analyzer's index and alarms,
tool, material and detector, times in seconds from the WAV's first sample; ``lathectl
analyze chatter FILE.wav`` reads both. Exit: 0 ok, 69 no daemon, 73 the file cannot be
written, 1/2 the daemon refused.
"""
from __future__ import annotations

import argparse
import base64
import json
import struct
import sys
import time
from pathlib import Path

from lathed.cli import EX_CANTCREAT, count, fail, positive

FORMAT = "lathed-recording/1"
MAX_GAP_S = 60.0        # a gap longer than this ends the recording (zeros for a minute say enough)


class WavWriter:
    """A mono IEEE-float WAV written as it comes; the sizes are set at close."""

    def __init__(self, path: Path, rate: float) -> None:
        self.path, self.rate, self.frames = path, rate, 0
        self.f = path.open("wb")
        self.f.write(self._header(0))

    def _header(self, frames: int) -> bytes:
        data = 4 * frames
        fmt = struct.pack("<HHIIHHH", 3, 1, int(round(self.rate)), 4 * int(round(self.rate)), 4, 32, 0)
        fact = struct.pack("<I", frames)
        return (b"RIFF" + struct.pack("<I", 4 + 8 + len(fmt) + 8 + len(fact) + 8 + data) + b"WAVE"
                + b"fmt " + struct.pack("<I", len(fmt)) + fmt + b"fact" + struct.pack("<I", 4) + fact
                + b"data" + struct.pack("<I", data))

    def write(self, raw: bytes) -> None:
        self.f.write(raw)
        self.frames += len(raw) // 4

    def close(self) -> None:
        self.f.seek(0)
        self.f.write(self._header(self.frames))
        self.f.close()


class Capture:
    """The stream's blocks into the WAV, and what to map host times to the WAV's seconds."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.wav: WavWriter | None = None
        self.rate: float | None = None
        self.next_seq: int | None = None
        self.first_seq: int | None = None
        self.clock: list[list[float]] = []        # [sample offset, host time of it], one a second
        self.gaps: list[list[float]] = []         # [WAV second, samples lost there]
        self.keyphasor: list[list[float]] = []    # [WAV second, r/min] where the block carried one
        self.stop: str | None = None
        self._last = [0, 0.0]                     # [samples written, host time just after them]
        self._offs: list[int] = []                # every block's first sample and its date, to map
        self._t0s: list[float] = []               # the samples' host times exactly

    def block(self, seq: int, t0: float, rpm: float | None, rate: float, b64: str) -> None:
        raw = base64.b64decode(b64)
        if self.wav is None:
            self.rate, self.first_seq, self.next_seq = rate, seq, seq
            self.block_len = len(raw) // 4
            self.wav = WavWriter(self.path, rate)
        if rate != self.rate:
            self.stop = f"the sensor's rate changed from {self.rate:g} to {rate:g} Hz"
            return
        if seq > self.next_seq:
            lost = seq - self.next_seq
            if lost > MAX_GAP_S * rate:
                self.stop = f"the stream was gone for {lost / rate:.0f} s"
                return
            self.gaps.append([round(self.wav.frames / rate, 6), lost])
            self.wav.write(bytes(4 * lost))
        elif seq < self.next_seq:           # a restarted stream counted from an earlier index
            self.gaps.append([round(self.wav.frames / rate, 6), 0])
        offset = self.wav.frames
        # the sidecar's clock: a point a second, and one wherever the daemon's dating of the
        # blocks stepped (its line re-anchored: a stalled device, an overrun)
        if not self.clock or offset - self.clock[-1][0] >= rate or abs(t0 - self._last[1]) > 5e-4:
            self.clock.append([offset, t0])
        self._offs.append(offset)
        self._t0s.append(t0)
        if rpm is not None and (not self.keyphasor or abs(rpm - self.keyphasor[-1][1]) > 1e-3 * rpm):
            self.keyphasor.append([round(offset / rate, 6), rpm])
        self.wav.write(raw)
        self.next_seq = seq + len(raw) // 4
        self._last = [offset + len(raw) // 4, t0 + len(raw) // 4 / rate]

    def seconds(self, t: float) -> float:
        """A host time as seconds from the WAV's first sample: within the block it falls in, as
        the daemon dated that block (before the first or after the last, at the device's rate)."""
        import bisect
        if not self._t0s:
            return 0.0
        k = max(0, bisect.bisect_right(self._t0s, t) - 1)
        return round((self._offs[k] + (t - self._t0s[k]) * self.rate) / self.rate, 6)


def sidecar(first: dict, cap: Capture, samples: list, why: str) -> dict:
    ctx = first.get("context") or {}
    sensor = first.get("sensor") or {}
    machine, analyzer = ctx.get("machine"), ctx.get("analyzer")

    def track(src, quantity):
        return [[cap.seconds(t), v] for t, s, q, v in samples if s == src and q == quantity]

    cuts, start = [], None
    for t, v in track(analyzer, "cutting"):
        if v and start is None:
            start = t
        elif not v and start is not None:
            cuts.append([start, t])
            start = None
    if start is not None:
        cuts.append([start, None])
    tools = track(machine, "tool_number")
    return {
        "format": FORMAT, "wav": cap.path.name, "source": first["source"], "plugin": first.get("plugin"),
        "daemon": first.get("daemon"), "rate_hz": cap.rate, "samples": cap.wav.frames,
        "duration_s": round(cap.wav.frames / cap.rate, 6), "block": cap.block_len,
        "quantity": sensor.get("quantity", "acceleration"), "unit": sensor.get("unit", "m/s²"),
        "sensitivity": sensor.get("calibration"), "sensor": sensor,
        "start": {"seq": cap.first_seq, "host_t": cap.clock[0][1] if cap.clock else None},
        "clock": cap.clock, "gaps": cap.gaps,
        "machine": machine, "analyzer": analyzer, "tool": ctx.get("tool"), "material": ctx.get("material"),
        "tool_number": tools[-1][1] if tools else None, "detector": ctx.get("detector"),
        "params": ctx.get("params") or {}, "cut_from": ctx.get("cut_from"),
        "speed": track(machine, "spindle_rpm"), "speed_keyphasor": cap.keyphasor,
        "cuts": cuts, "alarms": track(analyzer, "chatter_alarm"), "index": track(analyzer, "chatter_index"),
        "chatter_frequency_hz": track(analyzer, "chatter_frequency_hz"), "blind": track(analyzer, "blind"),
        "ended": why,
    }


def run(args: argparse.Namespace) -> int:
    from lathed.client import subscribe
    req = {"source": args.sensor, "pre_s": args.pre, "post_s": args.post}
    if args.cuts is not None:
        req.update(cuts=args.cuts, wait_s=args.wait)
    else:
        req["seconds"] = args.seconds
    out = Path(args.output or f"{args.sensor}-{time.strftime('%Y%m%d-%H%M%S')}.wav")
    side = out.with_suffix(".json")
    if out.suffix.lower() != ".wav":
        return fail(f"{out}: the recording is a WAV file: give a name ending in .wav (-o)", 2)
    for p in (out, side):
        if p.exists() and not args.force:
            return fail(f"{p} exists: give another name (-o) or --force", EX_CANTCREAT)
    stream = subscribe(req, sock_path=args.socket, timeout=max(10.0, 2 * args.pre + 5), cmd="record")
    first = next(stream)
    cap = Capture(out)
    samples: list = []
    why = "interrupted"
    try:
        for frame in stream:
            for blk in frame.get("blocks", ()):
                cap.block(*blk)
                if cap.stop:
                    break
            samples.extend(frame.get("samples", ()))
            if cap.stop or "end" in frame:
                why = cap.stop or frame["end"]["why"]
                break
    except KeyboardInterrupt:
        pass
    except OSError as e:
        return fail(f"cannot write {out}: {e.strerror or e}", EX_CANTCREAT)
    finally:
        stream.close()
    if cap.wav is None:
        return fail(f"nothing recorded from {args.sensor}: {why}", 1)
    cap.wav.close()
    meta = sidecar(first, cap, samples, why)
    try:
        side.write_text(json.dumps(meta, indent=1, default=str) + "\n")
    except OSError as e:
        return fail(f"cannot write {side}: {e.strerror or e}", EX_CANTCREAT)
    if args.json:
        print(json.dumps({"wav": str(out), "sidecar": str(side), **{k: meta[k] for k in (
            "duration_s", "rate_hz", "samples", "cuts", "alarms", "gaps", "ended")}}))
    else:
        alarms = sum(1 for _, v in meta["alarms"] if v)
        print(f"{out}: {meta['duration_s']:.2f} s of {args.sensor} at {cap.rate:g} Hz ({meta['unit']}), "
              f"{len(meta['cuts'])} cut(s), {alarms} chatter alarm(s); {why}")
        if cap.gaps:
            print(f"note: {sum(n for _, n in cap.gaps)} samples lost in {len(cap.gaps)} gap(s), zeros in the WAV "
                  f"(listed in {side.name})")
        print(f"beside it: {side}")
    return 0 if why != "interrupted" else 130


def register(sub) -> None:
    p = sub.add_parser("record", help="record a vibration sensor to a WAV file (and a JSON sidecar)",
                       description="Record a vibration sensor's samples, as the analyzers get them, to a 32-bit "
                                   "float WAV at the device's rate, with a JSON sidecar: calibration, spindle speed, "
                                   "cut state, chatter index and alarms, tool and material.")
    p.add_argument("sensor", help="the sensor's name ([sensor.NAME])")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--seconds", type=positive, metavar="S", help="record this long")
    what.add_argument("--cuts", type=count, metavar="N", help="record the next N cuts (from --pre before the "
                                                              "first to --post after the last)")
    p.add_argument("-o", "--output", metavar="FILE.wav", help="the WAV (default SENSOR-DATE-TIME.wav); "
                                                              "the sidecar is FILE.json")
    p.add_argument("--pre", type=float, default=1.0, metavar="S", help="--cuts: seconds before the first cut "
                                                                       "(the air; default 1)")
    p.add_argument("--post", type=float, default=0.5, metavar="S", help="--cuts: seconds after the last (0.5)")
    p.add_argument("--wait", type=positive, default=3600.0, metavar="S",
                   help="--cuts: give up when no cut starts within this (default 3600)")
    p.add_argument("--force", action="store_true", help="overwrite FILE.wav and FILE.json")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)
