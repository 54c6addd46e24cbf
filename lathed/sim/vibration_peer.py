"""The simulated accelerometer DAQ: a TCP stream of framed samples (lathed.wire)."""
from __future__ import annotations

import asyncio

import numpy as np

from lathed.wire import pack_vibration


class VibrationPeer:
    def __init__(self, host: str, port: int, rate_hz: int):
        self.host, self.port, self.rate_hz = host, port, rate_hz
        self.clients: set[asyncio.StreamWriter] = set()
        self.server: asyncio.AbstractServer | None = None
        self.seq = 0

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._client, self.host, self.port)

    async def stop(self) -> None:
        if self.server:
            self.server.close()
            for w in list(self.clients):
                w.close()
            self.clients.clear()
            await self.server.wait_closed()
            self.server = None

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.clients.add(writer)
        try:
            await reader.read()          # the stream is one-way; wait for the client to go
        except (ConnectionError, asyncio.CancelledError):
            pass     # cancelled at stop: ending quietly spares asyncio's traceback (Python 3.11)
        finally:
            self.clients.discard(writer)
            writer.close()

    def send(self, t0: float, rpm: float, data: np.ndarray) -> None:
        frame = pack_vibration(self.seq, t0, rpm, self.rate_hz, data)
        self.seq += len(data)
        for w in list(self.clients):
            if w.transport.get_write_buffer_size() > 8 << 20:
                w.close()                # a reader 8 MB behind is gone; it reconnects
                self.clients.discard(w)
                continue
            w.write(frame)
