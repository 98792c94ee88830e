"""The relay's Socket.IO server, hardened against clients that do not speak the protocol.

Every connection that sends something Engine.IO or Socket.IO cannot parse is closed at once,
without a logged traceback; the relay's own namespaces (relay.ingest, relay.uiapi) close the
ones that parse but make no sense. Relies on internals of python-socketio 5.x and
python-engineio 4.x (``_handle_eio_message``, ``_handle_event``, the driver table, the socket
queue); tests/relay/test_fuzz.py guards them.
"""

from __future__ import annotations

import logging

import socketio
from engineio import packet as eio_packet
from engineio.async_drivers import aiohttp as aiohttp_driver
from socketio import packet as sio_packet

RESERVED_EVENTS = frozenset({"connect", "disconnect", "connect_error"})

log = logging.getLogger(__name__)


class GuardedWebSocket(aiohttp_driver.WebSocket):
    """Engine.IO's aiohttp websocket wrapper, ending the session on an undecodable frame.

    Engine.IO decodes each frame in its websocket handler without a guard: a text frame that is
    no Engine.IO packet raises out of the request handler (a logged traceback per frame) and
    leaves the session behind until its ping times out. Reporting such a frame as the end of
    the connection (None) takes Engine.IO's own orderly close path instead.
    """

    async def wait(self):
        message = await super().wait()
        if isinstance(message, str):
            try:
                kind = eio_packet.Packet(encoded_packet=message).packet_type
            except Exception as exc:  # noqa: BLE001 - whatever the decoder rejects
                log.info("closing connection: not an Engine.IO packet: %s", str(exc)[:100])
                return None
            if not 0 <= kind < len(eio_packet.packet_names):
                log.info("closing connection: unknown Engine.IO packet type %d", kind)
                return None
        return message


class JsonPacket(sio_packet.Packet):
    """Socket.IO packets of a server that sends JSON only.

    The stock packet walks every list and dict of an outgoing message looking for bytes to
    send as attachments; for a push of a few thousand frames that walk cost more than making
    the push. The relay never sends binary, so a look at the top level is enough.
    """

    @classmethod
    def data_is_binary(cls, data) -> bool:
        if isinstance(data, (bytes, bytearray)):
            return True
        if isinstance(data, (list, tuple)):
            return any(isinstance(item, (bytes, bytearray)) for item in data)
        return False


class GuardedServer(socketio.AsyncServer):
    """An AsyncServer that closes a connection whose packets it cannot parse.

    python-socketio logs a traceback for a malformed packet and keeps the connection; a client
    sending garbage gets closed here instead. It also refuses binary packets announcing more
    than one attachment (the protocol uses exactly one), which would otherwise be buffered.
    Relies on ``_handle_eio_message`` of python-socketio 5.x and on python-engineio 4.x's
    driver table and socket queue; tests/relay/test_fuzz.py guards all three.
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.eio._async = dict(self.eio._async, websocket=GuardedWebSocket)

    async def _handle_eio_message(self, eio_sid, data):
        try:
            await super()._handle_eio_message(eio_sid, data)
            pending = self._binary_packet.get(eio_sid)
            if pending is not None and pending.attachment_count > 1:
                raise ValueError("too many binary attachments")
        except Exception as exc:  # noqa: BLE001 - any unparsable packet closes its connection
            log.info("closing connection %s: malformed packet: %s", eio_sid, str(exc)[:100])
            self._binary_packet.pop(eio_sid, None)
            await self.hang_up(eio_sid)

    async def _handle_event(self, eio_sid, namespace, id, data):
        # A client may not raise the server's own lifecycle events ("connect" would reach
        # on_connect with the client's data as its environ).
        if not (isinstance(data, list) and data and isinstance(data[0], str)) or data[0] in RESERVED_EVENTS:
            raise ValueError("malformed or reserved event")
        await super()._handle_event(eio_sid, namespace, id, data)

    async def hang_up(self, eio_sid: str) -> None:
        """Close a client's Engine.IO session and its websocket now.

        ``eio.disconnect`` only queues Engine.IO's CLOSE packet; the websocket itself would
        stay open until the client leaves or ping_interval + ping_timeout pass. The None in
        the socket's queue is what Engine.IO's own reader uses to make its writer close it.
        """
        socket = self.eio.sockets.pop(eio_sid, None)
        if socket is None:
            return
        # As eio.disconnect, without waiting for the writer to drain its queue: a writer whose
        # client already left never would.
        await socket.close(wait=False, reason=self.eio.reason.SERVER_DISCONNECT)
        socket.queue.put_nowait(None)
