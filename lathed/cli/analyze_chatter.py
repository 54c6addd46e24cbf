"""``lathectl analyze chatter``: run a chatter detector over a recording.

    lathectl analyze chatter FILE --rpm N [--rate HZ] [--channel K] [--var NAME]
        [--reference REF] [--detector NAME] [--param KEY=VALUE ...] [--json] [--plot OUT.png]
    lathectl analyze chatter REC.wav     (made by lathectl record: its sidecar REC.json
                                          gives the speed, the cuts and the detector)
    lathectl analyze chatter --params [NAME]     (a detector's options, then exit)

FILE is WAV, CSV (time_s and value columns, or one column with --rate), a
MATLAB .mat (--var names the variable: samples, or time and value columns; v7.3
needs the recordings extra) or an NI TDMS file (--var GROUP/CHANNEL; the
recordings extra). A WAV from ``lathectl record`` is replayed as the live analyzer ran
(lathed.analysis.replay): each cut from its start, at the recorded speed, with the
detector and parameters it used (--rpm, --detector, --param override them); the JSON adds
cuts_s and live_alarm_spans_s (what the daemon raised while recording).

``--json`` prints one object: verdict, reason, first_alarm_s,
chatter_frequency_hz, detector, evidence (the verdict without a reference:
lathed.analysis.chatter.verdict), windows [{t_s, index, alarm}], plus
clipped_samples, rate_hz, duration_s and notes. The verdict is "chatter" (an
onset found, or the whole recording's vibration is chatter's: one band near a
mode dominating the floor, or self-excited), "stable" (no onset against
--reference; without one, a broadband Gaussian vibration whose level held) or
"unknown" (the evidence is ambiguous: the reason says why).  --mains-hz names
the mains frequency whose multiples are not chatter (default both 50 and 60).
Exit: 0 ok, 2 usage, 66 file missing/unreadable, 65 data invalid, 69 a reader
not installed (the extra named), 73 plot cannot be written.
"""
from __future__ import annotations

import argparse
import json
import math
import sys

from lathed.cli import EX_CANTCREAT, EX_DATAERR, EX_NOINPUT, EX_UNAVAILABLE, once, positive, spindle_rpm

# numpy and the detectors are imported when the command runs: lathectl's other
# commands start without them (the names below are checked against the registry)
BUILTIN_DETECTORS = ("chaos_sync", "spectral_ratio", "sync_cusum", "sync_residual")
DEFAULT_DETECTOR = "sync_cusum"

BLOCK = 4096


def _channel(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a channel number") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"channel {v} must be >= 0 (channels count from 0)")
    return v


def _param(text: str) -> tuple[str, float]:
    key, eq, value = text.partition("=")
    try:
        if not eq or not key.strip():
            raise ValueError
        return key.strip(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not KEY=NUMBER (e.g. threshold=2)") from None


def _mains(text: str) -> tuple[float, ...]:
    try:
        hz = tuple(float(v) for v in text.split(","))
    except ValueError:
        hz = ()
    if not hz or not all(40.0 <= v <= 70.0 for v in hz):
        raise argparse.ArgumentTypeError(f"{text!r} is not a mains frequency (50, 60 or 50,60)")
    return hz


class _ListParams(argparse.Action):
    """--params [NAME]: print a built-in detector's options (default, range, meaning) and exit,
    as --help does: FILE and --rpm are not needed."""

    def __call__(self, parser, namespace, values, option_string=None):
        from lathed.analysis.chatter.registry import describe_params
        try:
            spec = describe_params(values)
        except ValueError as e:
            parser.exit(2, f"lathectl: {e} (--params)\n")
        print(f"{values} options ([analyzer.chatter.params] in lathed.toml, or --param KEY=VALUE):")
        for key, (default, lo, hi, meaning) in sorted(spec.items()):
            print(f"  {key:<16} {default:<8g} [{lo:g}, {hi:g}]  {meaning}")
        parser.exit(0)


def register_analyze(sub) -> None:
    p = sub.add_parser("chatter", help="detect chatter in a vibration recording (WAV, CSV, .mat or TDMS)",
                       description="Run a chatter detector over a recorded accelerometer signal. "
                                   "The baseline is learned from the first revolutions of the "
                                   "recording, or from --reference (a stable cut).")
    p.add_argument("file", metavar="FILE", help="WAV (PCM 16/24/32-bit or float), CSV "
                   "(time_s plus one signal column, or one column with --rate), MATLAB .mat or NI TDMS")
    p.add_argument("--var", metavar="NAME", help="variable of a .mat file or GROUP/CHANNEL (or a unique "
                   "CHANNEL) of a TDMS file (default: its only numeric one); a .mat's first column of "
                   "evenly increasing times is the time")
    p.add_argument("--rpm", type=spindle_rpm, help="spindle speed in r/min (required but for a "
                   "lathectl record WAV, whose sidecar has the speed over time)")
    p.add_argument("--rate", type=positive, metavar="HZ", help="sample rate of a CSV without time_s")
    p.add_argument("--channel", type=_channel, default=0, metavar="K",
                   help="WAV channel / CSV signal column, from 0 (default 0)")
    p.add_argument("--reference", metavar="REF", help="recording of a stable cut at the same speed "
                   "to learn the baseline from")
    p.add_argument("--detector", metavar="NAME",
                   help=f"one of {', '.join(BUILTIN_DETECTORS)} or a plugin's (default {DEFAULT_DETECTOR})")
    p.add_argument("--param", type=_param, action="append", default=[], metavar="KEY=VALUE",
                   help="a detector option, as in [analyzer.chatter.params] (repeat for more)")
    p.add_argument("--params", action=_ListParams, nargs="?", const=DEFAULT_DETECTOR, metavar="NAME",
                   help=f"list a built-in detector's options and exit (default {DEFAULT_DETECTOR})")
    p.add_argument("--mains-hz", type=_mains, default=(50.0, 60.0), metavar="HZ",
                   help="the mains frequency, whose multiples are hum, not chatter: 50, 60 or 50,60 "
                        "(default 50,60)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", metavar="OUT.png", help="write chaos eye and index over time")
    p.set_defaults(func=run)


def _err(msg: str) -> None:
    print(f"lathectl: {msg}", file=sys.stderr)


def _run_detector(det, x, rpm: float):
    wins = []
    for i in range(0, len(x), BLOCK):
        wins += det.process(x[i:i + BLOCK], rpm)
    return wins


def run(args, extra_detectors: dict | None = None) -> int:
    import numpy as np

    from lathed.analysis.chatter.registry import DETECTORS, make_detector
    from lathed.analysis.chatter.verdict import Verdict, judge
    from lathed.analysis.recording import RecordingError, read_sidecar, read_signal, takes_var
    from lathed.analysis.replay import live_spans, replay
    from lathed.wire import VIB_RATE_MAX, VIB_RATE_MIN

    if args.rpm is not None and not (args.rpm > 0 and math.isfinite(args.rpm)):
        _err(f"spindle speed must be > 0 r/min, got {args.rpm} (--rpm)")
        return 2
    params = once(getattr(args, "param", None) or [], "--param")
    if params is None:
        return 2
    try:
        var = getattr(args, "var", None)
        sig = read_signal(args.file, args.channel, args.rate, var)
        side = read_sidecar(args.file)
        if side is None and args.rpm is None:
            _err(f"--rpm is required: {args.file} has no sidecar from lathectl record to give the speed")
            return 2
        # --var names FILE's variable: a reference of another format (a WAV) is read without it
        ref = (read_signal(args.reference, args.channel, args.rate, var if takes_var(args.reference) else None)
               if args.reference else None)
    except RecordingError as e:
        _err(str(e))
        return 2 if e.usage else EX_NOINPUT if e.missing else EX_UNAVAILABLE if e.unavailable else EX_DATAERR
    if not VIB_RATE_MIN <= sig.rate_hz <= VIB_RATE_MAX:
        _err(f"sample rate {sig.rate_hz:g} Hz is outside the {VIB_RATE_MIN:g}..{VIB_RATE_MAX:g} Hz of an "
             f"accelerometer recording ({args.file})")
        return EX_DATAERR
    if side is not None:
        # the detector the daemon ran, unless told otherwise; the exact device rate (a WAV
        # header holds whole hertz)
        args.detector = args.detector or side.get("detector") or DEFAULT_DETECTOR
        params = params or dict(side.get("params") or {})
        sig.rate_hz = float(side["rate_hz"]) if round(side["rate_hz"]) == sig.rate_hz else sig.rate_hz
    args.detector = args.detector or DEFAULT_DETECTOR
    try:
        det = make_detector(args.detector, sig.rate_hz, extra=extra_detectors, **params)
    except ValueError as e:
        known = args.detector in DETECTORS or args.detector in (extra_detectors or {})
        if known and any(k in str(e) for k in params):     # the message names the bad option
            _err(f"{e} (--param)")
            return 2
        _err(f"{e} ({args.file if known else '--detector'})")
        return EX_DATAERR if known else 2
    try:
        if ref is not None:
            if abs(ref.rate_hz - sig.rate_hz) > 1e-6 * sig.rate_hz:
                _err(f"reference rate {ref.rate_hz:g} Hz differs from the recording's "
                     f"{sig.rate_hz:g} Hz ({args.reference})")
                return EX_DATAERR
            ref_rpm = args.rpm
            if ref_rpm is None:     # the recording's speed at its first cut
                from lathed.analysis.replay import speed_at
                ref_rpm = speed_at(side.get("speed_keyphasor") or side.get("speed") or [],
                                   (side.get("cuts") or [[0.0]])[0][0])
            det.learn_reference(ref.data, ref_rpm)
        if side is not None:
            wins, cut_spans = replay(det, sig.data, sig.rate_hz, side, args.rpm, side.get("block") or 1024)
        else:
            wins = _run_detector(det, sig.data, args.rpm)
    except ValueError as e:
        _err(f"{e} ({args.file})")
        return EX_DATAERR
    if not wins and det.too_slow and args.rpm is not None:
        _err(f"spindle speed {args.rpm:g} r/min is below the lowest the {det.name} detector "
             f"follows ({det.min_rpm:.0f} r/min at {sig.rate_hz:g} Hz) (--rpm)")
        return EX_DATAERR
    if not wins and side is not None:
        _err(f"no complete window in the recorded cuts ({len(side.get('cuts') or [])} cut(s) in "
             f"{sig.duration_s:.3g} s) ({args.file})")
        return EX_DATAERR
    if not wins:
        rev = 60.0 / args.rpm
        _err(f"recording is too short: {sig.duration_s:.3g} s holds no complete window at "
             f"{args.rpm:g} r/min (one revolution is {rev:.3g} s; several are needed) ({args.file})")
        return EX_DATAERR

    alarms = [w for w in wins if w.alarm]
    freqs = [w.chatter_frequency_hz for w in alarms if w.chatter_frequency_hz]
    mains = getattr(args, "mains_hz", (50.0, 60.0))
    if side is None:
        evidence = judge(sig.data, sig.rate_hz, args.rpm, mains)
    else:
        # a recording of the daemon's: its longest cut judged, at the speed recorded mid-way
        from lathed.analysis.replay import speed_at
        c0, c1 = max(cut_spans, key=lambda c: c[1] - c[0])
        rpm = args.rpm or speed_at(side.get("speed_keyphasor") or side.get("speed") or [], (c0 + c1) / 2)
        evidence = (judge(sig.data[int(c0 * sig.rate_hz):int(c1 * sig.rate_hz)], sig.rate_hz, rpm, mains)
                    if rpm else Verdict("unknown", "no spindle speed recorded for the cut", None, math.nan, math.nan))
    # a stable cut's level moves by less than the detector's allowance for it (cusum_ratio, else
    # its threshold)
    verdict, reason = _verdict(alarms, ref is not None, evidence, wins,
                               det.params.get("cusum_ratio") or det.threshold)
    out = {
        "verdict": verdict,
        "reason": reason,
        "first_alarm_s": round(alarms[0].t_s, 6) if alarms else None,
        # each alarm: raised, cleared (window ends; null: still on at the recording's end)
        "alarm_spans_s": [[round(a, 6), None if b is None else round(b, 6)] for a, b in _alarm_spans(wins)],
        "chatter_frequency_hz": round(float(np.median(freqs)), 2) if freqs else (
            evidence.as_dict()["frequency_hz"] if verdict == "chatter" else None),
        "evidence": evidence.as_dict(),
        "detector": det.name,
        "windows": [{"t_s": round(w.t_s, 6), "index": None if not math.isfinite(w.index) else
                     round(float(w.index), 4), "alarm": w.alarm} for w in wins],
        "clipped_samples": sig.clipped,
        "rate_hz": sig.rate_hz,
        "duration_s": round(sig.duration_s, 6),
        "notes": sig.notes,
        "baseline": "reference" if ref is not None else "recording start",
    }
    if side is not None:
        out.update(baseline="reference" if ref is not None else "each cut's start (as live)",
                   cuts_s=[[round(a, 6), round(b, 6)] for a, b in cut_spans],
                   live_alarm_spans_s=[[a, b] for a, b in live_spans(side.get("alarms") or [])],
                   speed_from="--rpm" if args.rpm is not None else
                   ("keyphasor" if side.get("speed_keyphasor") else f"{side.get('machine')} spindle_rpm"),
                   tool=side.get("tool"), material=side.get("material"), sensitivity=side.get("sensitivity"))
    caveat = []
    if sig.clipped:
        msg = (f"{sig.clipped} clipped samples (first at {sig.first_clip_s:.6g} s): the sensor or "
               f"converter saturated, amplitudes there are wrong ({args.file})")
        out["notes"] = out["notes"] + [msg]
        _err(f"warning: {msg}")
    if args.plot:
        code = _plot(args, sig, det, wins, side)
        if code:
            return code
    if args.json:
        print(json.dumps(out))
    else:
        speed = f"{args.rpm:g} r/min" if args.rpm is not None else f"speed from {out['speed_from']}"
        print(f"{args.file}: {out['verdict']}  ({det.name}, {len(wins)} windows, "
              f"{sig.duration_s:.3g} s at {sig.rate_hz:g} Hz, {speed})")
        print(f"why: {reason}")
        if side is not None:
            live = out["live_alarm_spans_s"]
            print(f"{len(out['cuts_s'])} cut(s) replayed as the daemon ran them; live, while recording: "
                  + (", ".join(f"alarm {a:.3f}-{b:.3f} s" if b is not None else f"alarm {a:.3f} s to the end"
                               for a, b in live) or "no alarm"))
        if alarms:
            f = out["chatter_frequency_hz"]
            print(f"first alarm at {out['first_alarm_s']:.4f} s"
                  + (f", chatter frequency {f:.1f} Hz" if f else ""))
            print("alarm on " + ", ".join(f"{a:.3f}-{b:.3f} s" if b is not None else f"{a:.3f} s to the end"
                                          for a, b in out["alarm_spans_s"]))
        for n in sig.notes + caveat:
            print(f"note: {n}")
    return 0


def _verdict(alarms, referenced: bool, evidence, wins, allowance: float) -> tuple[str, str]:
    """The recording's verdict and why: an onset the detector found; else, against a reference,
    stable; else the evidence of the whole recording (verdict.judge), a "stable" from it standing
    only where the level held (a stable cut's does; a recording that chatters from its first
    sample may be broad, yet its level wanders)."""
    if alarms:
        return "chatter", f"chatter grew within the recording: alarm at {alarms[0].t_s:.3f} s ({alarms[0].raised_by})"
    if referenced:
        return "stable", "no chatter onset against the stable reference"
    if evidence.verdict != "stable":
        return evidence.verdict, evidence.reason
    top = max((w.index for w in wins if w.judged and math.isfinite(w.index)), default=math.nan)
    if not top < allowance:
        comb = f"; the band is {evidence.comb}" if evidence.comb else ""
        return "unknown", (f"{evidence.reason}; but its level rose to {top:.2f} x its start (a stable "
                           f"cut's holds within {allowance:g} x){comb}: give --reference to tell")
    return "stable", f"{evidence.reason}; no chatter onset, its level held within {top:.2f} x its start"


def _alarm_spans(wins) -> list[tuple[float, float | None]]:
    """(raised, cleared) window times of each alarm; cleared None: still on at the end."""
    spans, t0 = [], None
    for w in wins:
        if w.alarm and t0 is None:
            t0 = w.t_s
        elif not w.alarm and t0 is not None:
            spans.append((t0, w.t_s))
            t0 = None
    if t0 is not None:
        spans.append((t0, None))
    return spans


def _plot(args, sig, det, wins, side=None) -> int:
    import numpy as np

    from lathed.analysis.chatter.registry import make_detector
    from lathed.analysis.replay import live_spans, replay

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # the chaos eye is drawn whatever detector decided
    eye = det if det.name == "chaos_sync" else make_detector("chaos_sync", sig.rate_hz)
    if eye is not det and side is not None:
        replay(eye, sig.data, sig.rate_hz, side, args.rpm, side.get("block") or 1024)
    elif eye is not det:
        _run_detector(eye, sig.data, args.rpm)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5))
    if eye.eye_baseline is not None:
        a1.scatter(*eye.eye_baseline, s=3, c="tab:blue", label="start of cut (baseline)")
    p1, p2 = eye.eye_points()
    if p1.size:
        a1.scatter(p1, p2, s=3, c="tab:red", alpha=0.5, label="last windows")
    a1.set_xlabel("φ1")
    a1.set_ylabel("φ2")
    a1.set_title("chaos eye")
    a1.legend(loc="upper right", fontsize=8)
    t = [w.t_s for w in wins]
    a2.semilogy(t, [w.index if math.isfinite(w.index) and w.index > 0 else np.nan for w in wins],
                label="index")
    a2.axhline(det.threshold, color="k", ls="--", lw=0.8, label="threshold")
    for k, (t0, t1) in enumerate(_alarm_spans(wins)):   # each alarm from raised to cleared
        a2.axvspan(t0, t[-1] if t1 is None else t1, color="tab:red", alpha=0.1, label="alarm" if k == 0 else None)
    if side is not None:
        for k, (c0, c1) in enumerate(side.get("cuts") or []):
            a2.axvspan(c0, t[-1] if c1 is None else c1, color="tab:green", alpha=0.06,
                       label="cut (daemon)" if k == 0 else None)
        for k, (l0, l1) in enumerate(live_spans(side.get("alarms") or [])):
            a2.plot([l0, t[-1] if l1 is None else l1], [det.threshold * 1.5] * 2, color="tab:purple", lw=3,
                    label="alarm (live)" if k == 0 else None)
        track = side.get("speed_keyphasor") or side.get("speed") or []
        # the speed before the recording began is its speed at 0 s
        before = [r for r in track if r[0] <= 0]
        track = ([[0.0, before[-1][1]]] if before else []) + [r for r in track if r[0] > 0]
        if track and args.rpm is None:
            a3 = a2.twinx()
            a3.step([r[0] for r in track] + [t[-1]], [r[1] for r in track] + [track[-1][1]], where="post",
                    color="tab:gray", lw=0.8)
            a3.set_ylabel("spindle speed (r/min)", color="tab:gray")
            a3.set_ylim(0, 1.25 * max(r[1] for r in track))
    a2.set_xlabel("time (s)")
    a2.set_ylabel(f"{det.name} index")
    a2.legend(fontsize=8)
    fig.tight_layout()
    try:
        fig.savefig(args.plot, dpi=110)
    except OSError as e:
        _err(f"cannot write the plot: {e.strerror} ({args.plot})")
        return EX_CANTCREAT
    finally:
        plt.close(fig)
    return 0
