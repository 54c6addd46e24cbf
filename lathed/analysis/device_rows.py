"""One device block's conditioned channels, handed with each channel's Block (``Block.rows``,
``Block.row``) so that the analyzers of a device's channels can do a block's numpy work for all
of them at once (docs/chatter.md, "The cost of a channel"). Pure numpy, no asyncio.
"""
from __future__ import annotations

import numpy as np


class DeviceRows:
    """The conditioned samples of one block of a device's channels (``ys``: one float32 array a
    channel, the very arrays its Blocks carry) and the block before (``prev``), for framing
    across the join. Made by the device's ConditionerBank once a block; it keeps the samples of
    the two latest blocks only (``release``): a reader two blocks behind works alone."""

    __slots__ = ("ys", "prev", "_key", "_rms")

    def __init__(self, ys: list[np.ndarray], prev: DeviceRows | None) -> None:
        self.ys: list[np.ndarray] | None = ys
        self.prev = prev
        self._key: tuple[int, int] | None = None
        self._rms: list[list[float]] | None = None

    def release(self) -> None:
        """The block after the next has come: the one before this is let go (its samples may
        outlive it in a recording's Blocks, and must not keep every channel's alive)."""
        if self.prev is not None:
            self.prev.ys = None
            self.prev = None

    def frame_rms(self, frame: int, k: int) -> list[list[float]] | None:
        """Each row's rms over frames of ``frame`` samples, the first starting ``k`` samples
        before this block (in the block before's row), the partial frame at the end left out:
        the numbers VibrationCutDetector.process makes for one row, bit for bit, for all rows
        in one set of numpy calls. None when it cannot be made here (the block before is
        gone, no whole frame, or it was asked with another framing: that reader works alone)."""
        if self._key is not None:
            return self._rms if self._key == (frame, k) else None
        ys, prev = self.ys, self.prev
        if ys is None:
            return None
        if k and (prev is None or prev.ys is None or len(prev.ys) != len(ys) or k > len(prev.ys[0])):
            return None
        n = len(ys[0])
        nf = (k + n) // frame
        if nf == 0:
            return None
        self._key = (frame, k)
        buf = np.empty((len(ys), nf * frame))       # float64, as the row alone is cast
        take = nf * frame - k
        if k:
            m = len(prev.ys[0])
            for i, (y0, y) in enumerate(zip(prev.ys, ys)):
                buf[i, :k] = y0[m - k:]
                buf[i, k:] = y[:take]
        else:
            for i, y in enumerate(ys):
                buf[i] = y[:take]
        frames = buf.reshape(len(ys), nf, frame)
        dev = frames - np.add.reduce(frames, axis=2, keepdims=True) / frame
        np.multiply(dev, dev, out=dev)
        ms = np.add.reduce(dev, axis=2)
        ms /= frame
        self._rms = np.sqrt(ms, out=ms).tolist()
        return self._rms
