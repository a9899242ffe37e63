"""An instrument's wrench as a serialized ``geometry_msgs/WrenchStamped``, filled in place.

The physics thread publishes a wrench every step: filling a message object and letting rclpy
convert it costs more than writing the stamp and six doubles into the CDR bytes rclpy's
``Publisher.publish`` accepts as they are. The bytes are taken once from
``rclpy.serialization.serialize_message`` of a template with the frame id (fixed for the
node's life); per message only the stamp (the first field: int32 sec, uint32 nanosec after
the 4-byte encapsulation) and the force and torque (six consecutive float64) change.

Invariant: ``deserialize_message(encode(force, torque, stamp), WrenchStamped)`` is the message
with that frame id, stamp, force and torque (checked in the tests).
"""

from __future__ import annotations

import struct

from geometry_msgs.msg import WrenchStamped
from rclpy.serialization import serialize_message

from .surface_marker import CDR_LE

_SENTINEL = (1.2345678901234567e-300, -7.654321098765432e-299, 3.1415926535897931e-297,
             2.718281828459045e-296, -1.4142135623730951e-295, 1.7320508075688772e-294)
_SIX = struct.Struct("<6d")
_STAMP = struct.Struct("<iI")


class WrenchEncoder:
    """Serialized WrenchStamped messages of one frame id."""

    def __init__(self, frame_id: str):
        m = WrenchStamped()
        m.header.frame_id = frame_id
        f, t = m.wrench.force, m.wrench.torque
        f.x, f.y, f.z, t.x, t.y, t.z = _SENTINEL
        raw = serialize_message(m)
        if raw[:2] != CDR_LE:
            raise RuntimeError(f"unexpected CDR encapsulation {raw[:4]!r}")
        data = _SIX.pack(*_SENTINEL)
        at = raw.find(data)
        if at < 0 or raw.find(data, at + 1) >= 0 or raw[4:12] != bytes(8):
            raise RuntimeError("cannot locate the stamp and wrench of a serialized WrenchStamped")
        self._buf = bytearray(raw)
        self._at = at

    def encode(self, force, torque, stamp_ns: int) -> bytes:
        """The serialized message with ``force`` and ``torque`` (3 floats each) stamped ``stamp_ns``."""
        buf = self._buf
        _STAMP.pack_into(buf, 4, int(stamp_ns // 1_000_000_000), int(stamp_ns % 1_000_000_000))
        _SIX.pack_into(buf, self._at, float(force[0]), float(force[1]), float(force[2]),
                       float(torque[0]), float(torque[1]), float(torque[2]))
        return bytes(buf)
