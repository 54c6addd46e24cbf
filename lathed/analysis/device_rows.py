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
    the two latest blocks only (``release``): a reader two blocks behind works alone.

    Framed work is grouped by its framing: a reader that took row ``r`` of a block says how it
    frames the next (``ask``), and the next block frames the rows asked alike together (channels
    that lost a block, or started later, frame at another offset: a group of their own)."""

    __slots__ = ("ys", "prev", "_extremes", "_asks", "_done")

    def __init__(self, ys: list[np.ndarray], prev: DeviceRows | None,
                 extremes: list[tuple[float, float]] | None = None) -> None:
        self.ys: list[np.ndarray] | None = ys
        self.prev = prev
        self._extremes = extremes      # each row's (lowest, highest) sample, when made with the rows
        self._asks: dict[tuple[int, int], list[int]] = {}
        self._done: dict[tuple[int, int], dict[int, list[float]]] = {}

    def release(self) -> None:
        """The block after the next has come: the one before this is let go (its samples may
        outlive it in a recording's Blocks, and must not keep every channel's alive)."""
        if self.prev is not None:
            self.prev.ys = None
            self.prev = None

    def extremes(self, row: int, data: np.ndarray) -> tuple[float, float] | None:
        """Row ``row``'s (lowest, highest) sample if ``data`` is that row and they were made
        with the rows (ConditionerBank); None: the caller reduces ``data`` itself."""
        ys, b = self.ys, self._extremes
        if b is None or ys is None or row >= len(b) or ys[row] is not data:
            return None
        return b[row]

    def ask(self, frame: int, k: int, row: int) -> None:
        """The reader of ``row`` will frame the next block's row by ``frame`` samples, the first
        frame starting ``k`` samples before it (the end of this block's row)."""
        self._asks.setdefault((frame, k), []).append(row)

    def frame_rms(self, frame: int, k: int, row: int) -> list[float] | None:
        """Row ``row``'s rms over frames of ``frame`` samples, the first starting ``k`` samples
        before this block (in the block before's row, which its reader took), the partial frame
        at the end left out: the numbers VibrationCutDetector.process makes for one row alone,
        bit for bit, made for every row asked alike in one set of numpy calls. None when it
        cannot be made here (the block before is gone, no whole frame, not asked): that reader
        works alone."""
        key = (frame, k)
        done = self._done.get(key)
        if done is None:
            done = self._done[key] = self._frames(frame, k)
        return done.get(row)

    def _frames(self, frame: int, k: int) -> dict[int, list[float]]:
        ys, prev = self.ys, self.prev
        if ys is None or prev is None or prev.ys is None:
            return {}
        n, m = len(ys[0]), len(prev.ys[0])
        rows = [r for r in prev._asks.get((frame, k), ()) if r < len(ys) and r < len(prev.ys)]
        nf = (k + n) // frame
        if not rows or nf == 0 or k > m:
            return {}
        buf = np.empty((len(rows), nf * frame))      # float64, as a row alone is cast
        take = nf * frame - k
        for i, r in enumerate(rows):
            buf[i, :k] = prev.ys[r][m - k:]
            buf[i, k:] = ys[r][:take]
        frames = buf.reshape(len(rows), nf, frame)
        dev = frames - np.add.reduce(frames, axis=2, keepdims=True) / frame
        np.multiply(dev, dev, out=dev)
        ms = np.add.reduce(dev, axis=2)
        ms /= frame
        return dict(zip(rows, np.sqrt(ms, out=ms).tolist()))
