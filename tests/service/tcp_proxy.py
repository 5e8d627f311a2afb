"""A TCP proxy in front of a real database for fault tests: ``forward`` (pass bytes both ways), ``down`` (every
connection cut, new ones refused: the database is gone) and ``hole`` (connections accepted, nothing passes either
way until the hole ends, when what was held flows on: a network partition that heals)."""

from __future__ import annotations

import asyncio
import threading


class TcpProxy:
    def __init__(self, target_host: str, target_port: int) -> None:
        self.target = (target_host, target_port)
        self.mode = "forward"
        self.port = 0
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="tcp-proxy", daemon=True)
        self._passing: asyncio.Event | None = None
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    def start(self) -> TcpProxy:
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self._listen(), self._loop).result(timeout=10)
        return self

    async def _listen(self) -> None:
        self._passing = asyncio.Event()
        self._passing.set()
        self._server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.mode == "down":
            writer.transport.abort()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.target)
        except OSError:
            writer.transport.abort()
            return
        self._writers |= {writer, up_writer}
        await asyncio.gather(self._pipe(reader, up_writer), self._pipe(up_reader, writer), return_exceptions=True)

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                await self._passing.wait()
                data = await reader.read(65536)
                if not data:
                    break
                await self._passing.wait()  # in a hole: held until it ends
                writer.write(data)
                await writer.drain()
        finally:
            self._writers.discard(writer)
            writer.transport.abort()

    def _set(self, mode: str) -> None:
        self.mode = mode
        if mode == "hole":
            self._passing.clear()
            return
        self._passing.set()
        if mode == "down":
            for writer in list(self._writers):
                writer.transport.abort()

    def set_mode(self, mode: str) -> None:
        """``forward``, ``down`` or ``hole`` (see the module docstring)."""
        if mode not in ("forward", "down", "hole"):
            raise ValueError(f"mode must be forward, down or hole, got {mode!r}")
        self._loop.call_soon_threadsafe(self._set, mode)

    def close(self) -> None:
        def stop() -> None:
            self._set("down")
            if self._server is not None:
                self._server.close()
            self._loop.stop()

        self._loop.call_soon_threadsafe(stop)
        self._thread.join(timeout=10)
