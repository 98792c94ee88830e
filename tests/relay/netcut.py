"""A TCP proxy between nodes and the relay that can cut the network: reset every connection
and refuse new ones, or black-hole the traffic (nothing closes, nothing gets through), or only
the relay's answers (``deaf``: the node's batches arrive, their acknowledgements do not)."""

from __future__ import annotations

import asyncio
import socket
import threading


class CutProxy:
    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.mode = "pass"  # pass | refuse | blackhole | deaf
        self._writers: set[asyncio.StreamWriter] = set()
        self._loop = asyncio.new_event_loop()
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", 0))
        self.port = sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self._thread = threading.Thread(target=self._run, args=(sock,), daemon=True)
        self._thread.start()

    def _run(self, sock: socket.socket) -> None:
        asyncio.set_event_loop(self._loop)
        self._loop.run_until_complete(asyncio.start_server(self._handle, sock=sock))
        self._loop.run_forever()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.mode == "refuse":
            writer.transport.abort()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            writer.transport.abort()
            return
        self._writers |= {writer, up_writer}
        await asyncio.gather(self._pump(reader, up_writer, ("blackhole",)),
                             self._pump(up_reader, writer, ("blackhole", "deaf")), return_exceptions=True)
        for w in (writer, up_writer):
            self._writers.discard(w)
            w.transport.abort()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, held: tuple[str, ...]) -> None:
        while True:
            data = await reader.read(65536)
            if not data:
                break
            while self.mode in held:
                await asyncio.sleep(0.02)
            writer.write(data)
            await writer.drain()
        writer.transport.abort()

    def cut(self, mode: str) -> None:
        """``refuse``: reset every connection and refuse new ones; ``blackhole``: stall them;
        ``deaf``: stall what the relay sends."""
        def apply() -> None:
            self.mode = mode
            if mode == "refuse":
                for w in list(self._writers):
                    w.transport.abort()
        self._loop.call_soon_threadsafe(apply)

    def restore(self) -> None:
        self._loop.call_soon_threadsafe(setattr, self, "mode", "pass")

    def close(self) -> None:
        self.cut("refuse")
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)
