"""Wire formats shared by the drivers and the simulator.

Vibration stream (TCP, one direction, server -> client), little-endian frames:

    magic    4s   b"LVIB"
    version  B    1
    channels B    number of interleaved channels (1 here)
    n        H    samples per channel in this frame
    rate     I    sample rate, Hz
    seq      Q    index of the frame's first sample since the stream began
    t0       d    time of the first sample, s since the Unix epoch
    rpm      f    actual spindle speed at the frame's start, r/min
    data     n*channels float32, acceleration in m/s²

``seq`` lets a reader see a gap (lost samples) or a restarted stream. A
header whose rate is outside what an accelerometer DAQ samples at
(VIB_RATE_MIN..VIB_RATE_MAX by default) or whose rpm is not a finite speed
>= 0 is well-formed but implausible: ``vibration_header_problem`` names it,
and the reader skips that frame's samples and stays in step.

Temperature line (serial, 115200 8N1, the Arduino with DS18B20 sensors), one
line per read cycle of all sensors:

    T,<seq>,<uptime_ms>,<name>=<celsius>[,<name>=<celsius>...]*<CCCC>\\r\\n

``seq`` counts read cycles since the Arduino booted (decimal digits only).
The checksum covers every byte from ``T`` up to (not including) ``*``; the
line announces which one by its length:

- four hex digits: CRC-16/CCITT-FALSE (polynomial 0x1021, initial 0xFFFF,
  not reflected, no final XOR; "123456789" gives 29B1), what the firmware
  sends now: it catches every burst of up to 16 bits, where
- two hex digits: the legacy XOR of the bytes, still accepted (a driver may
  refuse it), lets any two flips in the same bit column through.

A DS18B20 reads 85.0 on its first conversion after power-on and -127.0 when
it is disconnected; the Arduino sends what the sensor gave and the driver
rejects those.
"""
from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass

import numpy as np

VIB_HEADER = struct.Struct("<4sBBHIQdf")
VIB_MAGIC = b"LVIB"
VIB_VERSION = 1


def pack_vibration(seq: int, t0: float, rpm: float, rate_hz: int, data: np.ndarray) -> bytes:
    samples = np.asarray(data, dtype="<f4")
    channels = 1 if samples.ndim == 1 else samples.shape[1]
    n = samples.shape[0]
    return VIB_HEADER.pack(VIB_MAGIC, VIB_VERSION, channels, n, rate_hz, seq, t0, rpm) + samples.tobytes()


@dataclass(frozen=True)
class VibrationFrame:
    seq: int
    t0: float
    rpm: float
    rate_hz: int
    data: np.ndarray    # shape (n,) for one channel, else (n, channels)


class FrameError(ValueError):
    pass


def unpack_vibration_header(head: bytes) -> tuple[int, int, int, int, float, float]:
    """(channels, n, rate, seq, t0, rpm) from a header; FrameError if it is not one."""
    magic, version, channels, n, rate, seq, t0, rpm = VIB_HEADER.unpack(head)
    if magic != VIB_MAGIC:
        raise FrameError(f"bad frame magic {magic!r} (stream out of step or not a lathed vibration stream)")
    if version != VIB_VERSION:
        raise FrameError(f"unsupported frame version {version}")
    if channels < 1 or n < 1 or rate < 1:
        raise FrameError(f"malformed frame header: channels={channels} n={n} rate={rate}")
    return channels, n, rate, seq, t0, rpm


VIB_RATE_MIN, VIB_RATE_MAX = 100.0, 1_000_000.0    # Hz: what accelerometer DAQs sample at
VIB_RPM_MAX = 100_000.0


def vibration_header_problem(rate: float, rpm: float, rate_min: float = VIB_RATE_MIN,
                             rate_max: float = VIB_RATE_MAX) -> tuple[str, str] | None:
    """None if a decoded header is plausible, else (reason, one-line why)."""
    if not rate_min <= rate <= rate_max:
        return "rate", f"frame sample rate {rate:g} Hz outside the plausible {rate_min:g}..{rate_max:g} Hz"
    if not (math.isfinite(rpm) and 0.0 <= rpm <= VIB_RPM_MAX):
        return "rpm", f"frame spindle speed {rpm!r} r/min is not a finite speed in 0..{VIB_RPM_MAX:g}"
    return None


def xor_checksum(body: bytes) -> int:
    c = 0
    for b in body:
        c ^= b
    return c


def crc16(body: bytes) -> int:
    """CRC-16/CCITT-FALSE (0x1021, init 0xFFFF): on an Arduino, avr-libc's
    _crc_xmodem_update started from 0xFFFF."""
    return binascii.crc_hqx(body, 0xFFFF)


def format_temperature_line(seq: int, uptime_ms: int, readings: dict[str, float],
                            checksum: str = "crc16") -> bytes:
    body = f"T,{seq},{uptime_ms}," + ",".join(f"{k}={v:.4f}" for k, v in readings.items())
    raw = body.encode("ascii")
    if checksum == "xor8":
        return raw + b"*%02X\r\n" % xor_checksum(raw)
    return raw + b"*%04X\r\n" % crc16(raw)


class LineError(ValueError):
    pass


_HEX = frozenset(b"0123456789abcdefABCDEF")


def parse_temperature_line(line: bytes) -> tuple[int, int, dict[str, float], str]:
    """(seq, uptime_ms, {name: celsius}, checksum kind "crc16" | "xor8"); LineError naming what is wrong."""
    line = line.strip()
    if not line.startswith(b"T,"):
        raise LineError("does not start with 'T,'")
    body, star, check = line.rpartition(b"*")
    if not star:
        raise LineError("no '*' checksum")
    if len(check) not in (2, 4) or not _HEX.issuperset(check):
        raise LineError(f"checksum {check[:8]!r} is not 2 (XOR) or 4 (CRC-16) hex digits")
    kind, got = ("crc16", crc16(body)) if len(check) == 4 else ("xor8", xor_checksum(body))
    if got != int(check, 16):
        raise LineError(f"{kind} checksum mismatch (noise on the line?)")
    try:
        fields = body.decode("ascii").split(",")
        if len(fields) < 3 or not (fields[1].isdigit() and fields[2].isdigit()):
            raise ValueError(f"seq and uptime must be decimal digits, got {','.join(fields[1:3])!r}")
        seq, uptime = int(fields[1]), int(fields[2])
        readings = {}
        for f in fields[3:]:
            name, _, value = f.partition("=")
            if not name or not _:
                raise ValueError(f"field {f!r}")
            readings[name] = float(value)
    except (UnicodeDecodeError, ValueError) as e:
        raise LineError(f"malformed fields ({e})") from None
    return seq, uptime, readings, kind
