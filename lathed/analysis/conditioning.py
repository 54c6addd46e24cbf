"""Conditioning an audio-class sensor's samples: calibration to physical units, DC removal,
mains lines notched out, and a once-per-revolution keyphasor read as the spindle's speed and
phase on the device's own clock. Pure numpy/scipy, per block, state carried between blocks
(lathed.audio_device and plugins/audio_input.py use it; docs/sensors.md).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from lathed.analysis.device_rows import DeviceRows

# A non-finite sample makes its block non-finite here (inf - inf), which the plausibility gate
# refuses and says in one line (implausible_value, not_finite); numpy's own line adds nothing.
warnings.filterwarnings("ignore", "invalid value encountered", RuntimeWarning, __name__)

G0 = 9.80665             # m/s² per g
MAINS_WIDTH_HZ = 1.5     # each mains notch's width: the grid's frequency wanders by a tenth of a hertz


@dataclass(frozen=True)
class Calibration:
    """What a full-scale float sample (+-1.0) is in physical units."""
    scale: float             # unit per full scale
    quantity: str            # "acceleration" | "sound_pressure" | "vibration" (uncalibrated)
    unit: str                # "m/s²" | "Pa" | "FS"
    text: str                # how it was given, for status and a recording's sidecar

    @staticmethod
    def iepe(sensitivity_mv_g: float, full_scale_v: float) -> Calibration:
        """An analogue accelerometer (IEPE/ICP) into an interface whose full scale is ``full_scale_v``."""
        return Calibration(full_scale_v * 1000.0 / sensitivity_mv_g * G0, "acceleration", "m/s²",
                           f"{sensitivity_mv_g:g} mV/g, interface full scale {full_scale_v:g} V")

    @staticmethod
    def digital(counts_per_m_s2: float, bits: int) -> Calibration:
        """A digital (USB audio class) accelerometer: counts of its ``bits``-bit word per m/s²."""
        return Calibration(float(1 << (bits - 1)) / counts_per_m_s2, "acceleration", "m/s²",
                           f"{counts_per_m_s2:g} counts per m/s², {bits}-bit")

    @staticmethod
    def microphone(sensitivity_mv_pa: float, full_scale_v: float) -> Calibration:
        return Calibration(full_scale_v * 1000.0 / sensitivity_mv_pa, "sound_pressure", "Pa",
                           f"{sensitivity_mv_pa:g} mV/Pa, interface full scale {full_scale_v:g} V")

    @staticmethod
    def uncalibrated() -> Calibration:
        return Calibration(1.0, "vibration", "FS", "uncalibrated (full scale = 1)")


class OnePole:
    """w[n] = p w[n-1] + u[n] for a real pole 0 < p < 1, on whole blocks with numpy (scipy.signal
    would cost the daemon 70 MB and seconds to import): w = p^n (p w[-1] + cumsum(p^-n u)),
    in chunks short enough that p^-n stays below 1e4."""

    def __init__(self, p: float) -> None:
        self.p, self.w = float(p), 0.0
        self.chunk = max(16, int(9.2 / -math.log(self.p)))
        self._powers: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _power(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        if n not in self._powers:
            k = np.arange(n, dtype=np.float64)
            self._powers[n] = (self.p ** k, self.p ** -k)
        return self._powers[n]

    def run(self, u: np.ndarray) -> np.ndarray:
        if len(u) <= self.chunk:          # a block in one piece: the common case, no copy
            fwd, back = self._power(len(u))
            w = np.multiply(back, u)
            w.cumsum(out=w)                   # the method: np.cumsum's wrapper costs as much again
            w += self.p * self.w
            w *= fwd
            self.w = float(w[-1])
            return w
        out = np.empty(len(u))
        for i in range(0, len(u), self.chunk):
            seg = u[i:i + self.chunk]
            n = len(seg)
            fwd, back = self._power(n)
            w = fwd * (self.p * self.w + np.cumsum(back * seg))
            out[i:i + n] = w
            self.w = float(w[-1])
        return out

    def run_rows(self, u: np.ndarray, w0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``run`` along each row of ``u`` (rows x samples), row i from state ``w0[i]``: (the
        output, the new states). Each row's numbers are ``run``'s, bit for bit (the same
        operations, element by element; a cumulative sum runs in order along its row)."""
        n = u.shape[1]
        pw = (self.p * w0)[:, None]
        if n <= self.chunk:
            fwd, back = self._power(n)
            w = np.multiply(back, u)
            w.cumsum(axis=1, out=w)
            w += pw
            w *= fwd
            return w, w[:, -1].copy()
        out = np.empty(u.shape)
        for i in range(0, n, self.chunk):
            seg = u[:, i:i + self.chunk]
            fwd, back = self._power(seg.shape[1])
            w = fwd * (pw + np.cumsum(back * seg, axis=1))
            out[:, i:i + seg.shape[1]] = w
            pw = (self.p * w[:, -1])[:, None]
        return out, out[:, -1].copy()


class MainsComb:
    """Notches at the mains frequency and every harmonic of it: y[n] = x[n] - x[n-N] + rho y[n-N],
    N = rate / mains (a fraction of a sample read by linear interpolation), each notch
    ``width_hz`` wide at -3 dB, the gain between them within +0.5 dB. The delay is a whole
    mains period, so a block is worked in chunks of a period, each from history alone."""

    def __init__(self, rate_hz: float, mains_hz: float, width_hz: float = MAINS_WIDTH_HZ) -> None:
        period = rate_hz / mains_hz
        self.n0, self.frac = int(period), period - int(period)
        self.rho = min(0.999, max(0.5, 1.0 - math.pi * width_hz / mains_hz))
        self._hx: np.ndarray | None = None
        self._hy = np.zeros(self.n0 + 1)

    def run(self, x: np.ndarray) -> np.ndarray:
        if self._hx is None:
            self._hx = np.full(self.n0 + 1, x[0])      # as if the first level had always been there
        out = np.empty(len(x))
        f, hx, hy = self.frac, self._hx, self._hy
        for i in range(0, len(x), self.n0):
            c = x[i:i + self.n0]
            n = len(c)
            # hx[k] is x[start - n0 - 1 + k]: x[n - N] is between hx[j + 1] and hx[j]
            xd = (1 - f) * hx[1:1 + n] + f * hx[:n]
            yd = (1 - f) * hy[1:1 + n] + f * hy[:n]
            y = c - xd + self.rho * yd
            out[i:i + n] = y
            hx = np.concatenate((hx, c))[-(self.n0 + 1):]
            hy = np.concatenate((hy, y))[-(self.n0 + 1):]
        self._hx, self._hy = hx, hy
        if not math.isfinite(float(hx.sum() + hy.sum())):
            self.restart()
        return out

    def restart(self) -> None:
        """A non-finite sample would come back every period: the next block starts afresh."""
        self._hx, self._hy = None, np.zeros(self.n0 + 1)


class Conditioner:
    """Scale, then a first-order high-pass (DC removal, ``highpass_hz``; 0: off), then notches
    at the mains frequency and all its harmonics (``mains_hz``; 0: off). State runs on from
    block to block; numpy only."""

    def __init__(self, rate_hz: float, scale: float, highpass_hz: float = 0.0, mains_hz: float = 0.0) -> None:
        self.scale = float(scale)
        self._hp = None
        if highpass_hz > 0:
            # bilinear first-order high-pass: (1 + a) / 2 (1 - z^-1) / (1 - a z^-1)
            k = math.tan(math.pi * highpass_hz / rate_hz)
            a = (1 - k) / (1 + k)
            self._hp = (OnePole(a), (1 + a) / 2)
        self._x_last: float | None = None
        self.comb = MainsComb(rate_hz, mains_hz) if mains_hz > 0 else None

    def process(self, x: np.ndarray) -> np.ndarray:
        """One block of full-scale samples -> physical units (float32)."""
        y = np.multiply(x, self.scale, dtype=np.float64)    # x.astype(np.float64) * scale, in one pass
        if self._hp is not None:
            pole, g = self._hp
            if self._x_last is None:
                self._x_last = y[0]          # started at the first sample's level: no step from a DC offset
            dx = np.empty_like(y)
            dx[0] = y[0] - self._x_last
            np.subtract(y[1:], y[:-1], out=dx[1:])
            dx *= g
            self._x_last = y[-1]
            y = pole.run(dx)
            self._restart_if_not_finite()
        if self.comb is not None:
            y = self.comb.run(y)
        return y.astype(np.float32)

    def _restart_if_not_finite(self) -> None:
        """A non-finite sample (its block refused at the gate) would stay in the high-pass's
        state and make every later block non-finite: the channel blind until a restart. The
        next block starts afresh, as the first did."""
        if not (math.isfinite(self._x_last) and math.isfinite(self._hp[0].w)):
            self._x_last, self._hp[0].w = None, 0.0

    @staticmethod
    def process_rows(conds: list[Conditioner], x: np.ndarray, scale: np.ndarray) -> list[np.ndarray]:
        """Row i of ``x`` (channels x frames, full scale) through ``conds[i]`` (whose scales are
        ``scale``, a column), in one pass of numpy calls for all rows: each row's numbers are
        its own ``process``'s, bit for bit. The conditioners share their rate and high-pass."""
        return Conditioner.rows_and_extremes(conds, x, scale)[0]

    @staticmethod
    def rows_and_extremes(conds: list[Conditioner], x: np.ndarray,
                        scale: np.ndarray) -> tuple[list[np.ndarray], list[tuple[float, float]] | None]:
        """``process_rows``, and each row's (lowest, highest) sample as its float32 array's
        np.minimum/np.maximum.reduce gives them (None: not made here, with a mains notch or a
        single row): the plausibility gate's check of every block, one reduction for all rows
        (a reduction's call costs as much as its 1024 samples). Rounding to float32 keeps order,
        so the float64 rows' extremes rounded are the float32 rows' extremes, to the bit."""
        if len(conds) == 1:
            return [conds[0].process(x[0])], None
        # x.astype(np.float64) * scale: the cast, then the product in place (a cast inside a
        # broadcast multiply goes through numpy's buffered loop, twice the time)
        y = x.astype(np.float64)
        y *= scale
        hp = conds[0]._hp
        if hp is not None:
            g = hp[1]
            last = [c._x_last for c in conds]
            if None in last:                 # started at the first sample's level: no step from a DC offset
                last = [y[i, 0] if v is None else v for i, v in enumerate(last)]
            dx = np.empty_like(y)
            # each row's differences in one contiguous pass over all rows (a strided 2-D one
            # costs three times as much); the pairs that straddle two rows are overwritten next
            flat = y.reshape(-1)
            np.subtract(flat[1:], flat[:-1], out=dx.reshape(-1)[1:])
            np.subtract(y[:, 0], last, out=dx[:, 0])
            dx *= g
            for c, v in zip(conds, y[:, -1].tolist()):
                c._x_last = v
            # one pole's powers for all (the same rate and corner), each row from its own state
            y, w = hp[0].run_rows(dx, np.array([c._hp[0].w for c in conds]))
            for c, v in zip(conds, w.tolist()):
                c._hp[0].w = v
                c._restart_if_not_finite()
        out = []
        for c, row in zip(conds, y):
            out.append((row if c.comb is None else c.comb.run(row)).astype(np.float32))
        if any(c.comb is not None for c in conds):
            return out, None
        lo = np.minimum.reduce(y, axis=1).astype(np.float32).tolist()
        hi = np.maximum.reduce(y, axis=1).astype(np.float32).tolist()
        return out, list(zip(lo, hi))


class ConditionerBank:
    """The conditioners of the channels of one device that share a high-pass and a mains
    frequency (the audio_input sensors reading it, lathed.audio_device): a block of all its
    channels is conditioned in one pass (Conditioner.process_rows) when the first of them asks,
    so numpy's call overhead is paid once a block, not once a channel. Each member's samples
    are the ones its own Conditioner would give, bit for bit."""

    def __init__(self) -> None:
        self._members: dict[object, tuple[Conditioner, int]] = {}
        self._block: np.ndarray | None = None
        self._rows: dict[object, tuple] = {}
        self._last: DeviceRows | None = None     # the last block's rows
        self._order()

    def join(self, member: object, cond: Conditioner, column: int) -> None:
        """``member`` takes ``column`` (from 0) of each block through ``cond`` (fresh state)."""
        self._members[member] = (cond, column)
        self._rows.pop(member, None)
        self._order()

    def leave(self, member: object) -> None:
        if self._members.pop(member, None) is not None:
            self._order()

    def _order(self) -> None:
        """The members as rows: their keys, conditioners, columns and scales, made once."""
        self._keys = list(self._members)
        self._conds = [c for c, _ in self._members.values()]
        self._cols = np.array([col for _, col in self._members.values()], dtype=np.intp)
        self._scale = np.array([[c.scale] for c in self._conds], dtype=np.float64).reshape(-1, 1)
        self._top = int(self._cols.max()) if len(self._cols) else -1

    def take(self, member: object, data: np.ndarray) -> tuple[np.ndarray, float, np.ndarray | None,
                                                              tuple[DeviceRows, int] | None]:
        """The member's column of ``data`` (frames x channels, full scale), its peak |x|, its
        conditioned samples (float32; None for exact digital silence, which leaves its
        conditioner as it was) and where they lie in the block's DeviceRows (its rows and its
        row; None when conditioned alone). A block is conditioned once, for every member,
        whoever asks first."""
        if data is not self._block:
            self._rows = {}
            self._block = data
            self._rows = self._pass(data)
        got = self._rows.get(member)
        if got is None:     # joined after this block's pass (or a column the block lacks): its own
            cond, col = self._members[member]
            x = np.ascontiguousarray(data[:, col])
            peak = float(np.maximum.reduce(np.abs(x)))
            got = self._rows[member] = (x, peak, cond.process(x) if peak != 0.0 else None, None)
        return got

    def _pass(self, data: np.ndarray) -> dict:
        keys, conds, cols, scale = self._keys, self._conds, self._cols, self._scale
        if not keys:
            return {}
        if self._top >= data.shape[1]:
            # a member's column the block lacks fails on its own (take), as it would alone
            inside = np.flatnonzero(cols < data.shape[1])
            keys, conds = [keys[i] for i in inside], [conds[i] for i in inside]
            cols, scale = cols[inside], scale[inside]
            if not keys:
                return {}
        x = data.T[cols]                # a row a member, each contiguous
        peak = np.maximum.reduce(np.abs(x), axis=1).tolist()
        if 0.0 not in peak:
            ys, extremes = Conditioner.rows_and_extremes(conds, x, scale)
            rows = self._device_rows(ys, extremes)
            return {k: (x[i], peak[i], ys[i], (rows, i)) for i, k in enumerate(keys)}
        live = [i for i, p in enumerate(peak) if p != 0.0]
        out = {k: (x[i], peak[i], None, None) for i, k in enumerate(keys)}
        if live:
            ys, extremes = Conditioner.rows_and_extremes([conds[i] for i in live], x[live], scale[live])
            rows = self._device_rows(ys, extremes)
            for j, (i, y) in enumerate(zip(live, ys)):
                out[keys[i]] = (x[i], peak[i], y, (rows, j))
        return out

    def _device_rows(self, ys: list[np.ndarray], extremes: list[tuple[float, float]] | None) -> DeviceRows:
        """This block's rows for the analyzers, the block before kept beside them (and the one
        before that let go)."""
        last = self._last
        if last is not None:
            last.release()
        self._last = DeviceRows(ys, last, extremes)
        return self._last


class Keyphasor:
    """Once-per-revolution pulses (a proximity probe or an optical mark through an audio input,
    AC-coupled: a spike at each edge) -> the sample of each revolution's start, on the device's
    clock, and the speed over the last revolution.

    A revolution starts where the signal rises through half its running peak, re-armed once
    it has fallen below a fifth of it; pulses closer than a revolution at ``max_rpm`` are one.
    """

    def __init__(self, rate_hz: float, min_rpm: float = 30.0, max_rpm: float = 30000.0) -> None:
        self.rate = float(rate_hz)
        self.min_gap = self.rate * 60.0 / max_rpm
        self.max_gap = self.rate * 60.0 / min_rpm
        self.peak = 0.0
        self._decay = 0.5 ** (1.0 / (2.0 * self.rate))     # the peak halves in 2 s
        self._armed = True
        self._prev = 0.0                 # the last sample of the block before
        self.marks: list[float] = []     # revolution starts (stream sample index, fractional), recent
        self.pulses = 0
        self.revolution: float | None = None   # samples in the last revolution

    def process(self, x: np.ndarray, start: int) -> list[float]:
        """Samples ``start``.. of the stream; returns the revolution starts found in them."""
        x = np.asarray(x, dtype=np.float64)
        if len(x) == 0:
            return []
        top = float(np.max(np.abs(x)))
        if not math.isfinite(top):
            # read as 0 (below any pulse): an infinite peak would hold the threshold there for
            # good, and the block's real pulses are still read
            x = np.where(np.isfinite(x), x, 0.0)
            top = float(np.max(np.abs(x)))
        self.peak = max(top, self.peak * self._decay ** len(x))
        hi, lo = 0.5 * self.peak, 0.2 * self.peak
        found = []
        i = 0
        prev = self._prev
        while hi > 0 and i < len(x):
            if not self._armed:
                below = np.flatnonzero(x[i:] < lo)
                if below.size == 0:
                    break
                i += int(below[0])
                self._armed = True
            above = np.flatnonzero(x[i:] >= hi)
            if above.size == 0:
                break
            j = i + int(above[0])
            before = x[j - 1] if j > 0 else prev
            frac = (hi - before) / (x[j] - before) if x[j] != before else 0.0
            at = start + j - 1 + min(max(frac, 0.0), 1.0)
            self._armed = False
            if not self.marks or at - self.marks[-1] >= self.min_gap:
                if self.marks and at - self.marks[-1] <= self.max_gap:
                    self.revolution = at - self.marks[-1]
                self.marks = (self.marks + [at])[-64:]
                self.pulses += 1
                found.append(at)
            i = j + 1
        self._prev = float(x[-1])
        return found

    def rpm(self, now: int) -> float | None:
        """The speed at stream sample ``now``: over the last revolution, or lower where no pulse
        has come for a quarter revolution more than that (slowing down); None with no pulse for
        a revolution at min_rpm."""
        if self.revolution is None or not self.marks:
            return None
        since = now - self.marks[-1]
        if since > self.max_gap:
            return None
        return 60.0 * self.rate / (since if since > 1.25 * self.revolution else self.revolution)

    def phase(self, at: float) -> float | None:
        """The spindle angle (radians, 0 at the last pulse) at stream sample ``at``."""
        if self.revolution is None or not self.marks:
            return None
        return 2 * math.pi * ((at - self.marks[-1]) / self.revolution % 1.0)
