"""The capture helper: one process per audio input device, owning its PortAudio stream.

    python -m lathed.audio_capture --device NAME|INDEX [--hostapi NAME] --rate HZ
        --channels N --block FRAMES [--stall S]

The daemon (lathed.audio_device) starts it and reads its stdout: one text line,
``READY {json}`` (the device opened) or ``ERROR {json}`` (it was not), then binary
frames (FRAME below) until the stream fails or stdin closes. It is a process of
its own because PortAudio cannot be trusted to come back in-process: its JACK
host API hangs for ever in Pa_AbortStream/Pa_CloseStream once the server is
gone, and its device list is fixed until Pa_Terminate, which would close every
other device's stream. A fresh process per (re)connection finds a device that was
plugged in again, and a hung one is killed. Docs: docs/sensors.md.
"""
from __future__ import annotations

import argparse
import json
import os
import queue
import struct
import sys
import threading
import time

# magic, frames, channels, flags, adc time (the device stream's clock, s), host wall time of
# the first sample (s since epoch), blocks dropped here so far (the daemon did not read)
FRAME = struct.Struct("<4sIIIddI")
MAGIC = b"LAUD"
OVERFLOW, UNDERFLOW = 1, 2     # PortAudio's input overflow / underflow flags on this block
QUEUE_S = 2.0                  # seconds of blocks held for a daemon that reads late


def find_device(sd, spec: str, hostapi: str | None, channels: int) -> tuple[int, dict]:
    """The input device ``spec`` names: an index, or a case-insensitive part of its name
    (an exact name wins over a part); ``hostapi`` narrows to a host API (ALSA, JACK...)."""
    apis = sd.query_hostapis()
    devs = [(i, d) for i, d in enumerate(sd.query_devices()) if d["max_input_channels"] > 0]
    if hostapi:
        devs = [(i, d) for i, d in devs if hostapi.lower() in apis[d["hostapi"]]["name"].lower()]

    def listed(ds) -> str:
        return "; ".join(f"{i}: {d['name']} ({apis[d['hostapi']]['name']}, {d['max_input_channels']} in)"
                         for i, d in ds) or "none"
    if spec.isdigit():
        picked = [(i, d) for i, d in devs if i == int(spec)]
    else:
        picked = [(i, d) for i, d in devs if d["name"].lower() == spec.lower()] or \
                 [(i, d) for i, d in devs if spec.lower() in d["name"].lower()]
    if not picked:
        raise LookupError(f"no input device matching {spec!r}"
                          + (f" under host API {hostapi!r}" if hostapi else "") + f" (input devices: {listed(devs)})")
    if len(picked) > 1:
        raise LookupError(f"{spec!r} matches {len(picked)} input devices: {listed(picked)}; give its index, "
                          "its full name or hostapi")
    i, d = picked[0]
    if d["max_input_channels"] < channels:
        raise LookupError(f"{d['name']} has {d['max_input_channels']} input channels, {channels} needed")
    return i, {"index": i, "name": d["name"], "hostapi": apis[d["hostapi"]]["name"],
               "max_input_channels": d["max_input_channels"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lathed.audio_capture")
    p.add_argument("--device", required=True)
    p.add_argument("--hostapi")
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--channels", type=int, required=True)
    p.add_argument("--block", type=int, required=True)
    p.add_argument("--stall", type=float, default=1.0, help="no block for this long: the device is gone")
    a = p.parse_args(argv)
    out = sys.stdout.buffer

    def say(word: str, obj: dict) -> None:
        out.write(f"{word} {json.dumps(obj)}\n".encode())
        out.flush()
    try:
        import sounddevice as sd
    except OSError as e:       # the module is there, PortAudio (libportaudio2) is not
        say("ERROR", {"error": f"PortAudio is not installed ({e}): install the libportaudio2 package"})
        return 2
    try:
        index, info = find_device(sd, a.device, a.hostapi, a.channels)
    except LookupError as e:
        say("ERROR", {"error": str(e), "gone": True})
        return 3
    blocks: queue.Queue = queue.Queue(maxsize=max(4, int(QUEUE_S * a.rate / a.block)))
    dropped = [0]
    ended = threading.Event()

    def callback(data, frames, t, status) -> None:
        # PortAudio's thread: copy and hand over, never block
        now = time.time()
        adc = t.inputBufferAdcTime
        lag = t.currentTime - adc if adc and t.currentTime else frames / a.rate
        flags = (OVERFLOW if status.input_overflow else 0) | (UNDERFLOW if status.input_underflow else 0)
        try:
            blocks.put_nowait((bytes(data), frames, flags, adc, now - lag))
        except queue.Full:
            dropped[0] += 1
    try:
        stream = sd.RawInputStream(device=index, channels=a.channels, samplerate=a.rate, blocksize=a.block,
                                   dtype="float32", callback=callback, finished_callback=ended.set)
        stream.start()
    except Exception as e:     # PortAudioError, ValueError: a rate or channel count it refuses
        say("ERROR", {"error": f"{info['name']}: {e}"})
        return 3
    say("READY", {**info, "rate_hz": stream.samplerate, "latency_s": stream.latency, "pid": os.getpid()})
    def end_on_eof() -> None:
        # the daemon closing our stdin (or dying) is the end: the stream closed if it closes
        # in a second (the audio server gone, PortAudio's JACK host API hangs there for ever)
        sys.stdin.buffer.read()
        closing = threading.Thread(target=stream.close, daemon=True)
        closing.start()
        closing.join(1.0)
        os._exit(0)
    threading.Thread(target=end_on_eof, daemon=True).start()
    while True:
        try:
            data, frames, flags, adc, host_t = blocks.get(timeout=a.stall)
        except queue.Empty:
            why = "the stream stopped" if ended.is_set() or not stream.active else \
                f"no samples for {a.stall:g} s"
            sys.stderr.write(f"device gone: {info['name']}: {why}\n")
            sys.stderr.flush()
            # never close the stream: PortAudio's JACK host API hangs there once the server is gone
            os._exit(4)
        try:
            out.write(FRAME.pack(MAGIC, frames, a.channels, flags, adc, host_t, dropped[0]) + data)
            out.flush()
        except (BrokenPipeError, OSError):
            os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
