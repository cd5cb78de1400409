"""Robot side of steelscan: the wire protocol, the on-board client and the simulator."""

from robot_link.protocol import (
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    Message,
    MessageType,
    ProtocolError,
    decode_message,
    encode_message,
)

__all__ = [
    "MAX_MESSAGE_BYTES",
    "PROTOCOL_VERSION",
    "Message",
    "MessageType",
    "ProtocolError",
    "decode_message",
    "encode_message",
]
