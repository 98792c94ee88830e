"""The relay's Socket.IO packets (relay/api/sio.py's JsonPacket, which looks for bytes only among the
values of objects): byte for byte the stock packet's encoding of every message the relay sends, and
decoded by the stock packet into the message again."""

from __future__ import annotations

import numpy as np
from socketio import packet as sio_packet

from dcuscope.relay.api.sio import JsonPacket
from dcuscope.relay.live import framepack


def frames_push(dcus: int) -> list:
    stages = 5
    ints = np.arange(framepack.int_rows(stages) * 7, dtype=np.int64).reshape(-1, 7)
    floats = np.linspace(0, 1, framepack.float_rows(stages) * 7).reshape(-1, 7)
    blocks = {f"DCU-{i}": {"node": f"DCU-{i}", "stages": [f"s{k}" for k in range(stages)], "kinds": {"s0": "mux"},
                           "has_exit": [True] * stages, "cursor": 7, "packed": framepack.packed(ints, floats + i, stages)}
              for i in range(dcus)}
    return ["frames", {"t_ns": 1, "nodes": blocks}]


MESSAGES = [
    frames_push(1), frames_push(8),
    ["stats", {"nodes": {"DCU-1": {"stages": {"infer": {"count": 3, "p50_ms": 1.5}}, "fps": {"0": 25.0}}}}],
    ["nodes", [{"node": "DCU-1", "rows": [[1, 2], [3, None]]}]],
    ["overview", {"rows": [], "gone": ["DCU-9"]}],
    ["raw", b"\x00\x01", {"deep": {"deeper": bytearray(b"xy")}}],
]


def encode(cls, message: list):
    return cls(sio_packet.EVENT, namespace="/ui", data=message).encode()  # binary or not, as each finds


def test_every_message_is_encoded_as_the_stock_packet_encodes_it_and_decodes_back():
    for message in MESSAGES:
        ours, stock = encode(JsonPacket, message), encode(sio_packet.Packet, message)
        assert ours == stock, message[0]
        if isinstance(ours, list):  # a binary event: its attachments put back by the stock decoder
            decoded = sio_packet.Packet(encoded_packet=ours[0])
            for attachment in ours[1:]:
                decoded.add_attachment(attachment)
            assert decoded.data == message
    bytes_at = MESSAGES[1][1]["nodes"]["DCU-3"]["packed"]
    assert isinstance(bytes_at["ints"], bytes)  # the message itself is left as it was
