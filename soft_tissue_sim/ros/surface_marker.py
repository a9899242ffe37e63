"""The tissue surface as a serialized ``visualization_msgs/Marker`` (TRIANGLE_LIST), built from numpy.

A Marker's ``points`` is a sequence of ``geometry_msgs/Point`` objects: building one Python
object per vertex and converting them again when publishing costs milliseconds for a few
thousand triangles. Here the message is kept in its serialized form (CDR, the bytes rclpy's
``Publisher.publish`` accepts as they are): a fixed head (header, ns, id, type, pose, scale,
color...) and tail (the empty colors, texture, mesh and text fields) taken once from
``rclpy.serialization.serialize_message`` of the template, and between them the point count
and the vertex coordinates, which in CDR are exactly the float64 triples of a numpy (k, 3)
array. Per message only the stamp, the count and the coordinate bytes change.

Invariant: ``deserialize_message(encode(points, stamp), Marker)`` equals the template with
``points`` set from the array and ``header.stamp`` set (checked in the tests).
"""

from __future__ import annotations

import struct

import numpy as np
from geometry_msgs.msg import Point
from rclpy.serialization import serialize_message
from visualization_msgs.msg import Marker

_SENTINEL = (1.2345678901234567e-300, -7.654321098765432e-299, 3.1415926535897931e-297)
CDR_LE = b"\x00\x01"  # encapsulation: plain CDR, little endian (the serialized messages of the node)


def surface_template(frame_id: str) -> Marker:
    """The tissue's Marker without points: TRIANGLE_LIST, ns "tissue", id 0, pink, unit scale."""
    m = Marker()
    m.header.frame_id = frame_id
    m.ns, m.id, m.type, m.action = "tissue", 0, Marker.TRIANGLE_LIST, Marker.ADD
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 1.0
    m.color.r, m.color.g, m.color.b, m.color.a = 0.9, 0.55, 0.55, 1.0
    return m


class SurfaceMarkerEncoder:
    """Serialized Marker messages from (k, 3) vertex arrays (three vertices per triangle)."""

    def __init__(self, template: Marker):
        m = Marker()
        for f in m.get_fields_and_field_types():
            setattr(m, f, getattr(template, f))
        m.header.stamp.sec, m.header.stamp.nanosec = 0, 0
        m.points = [Point(x=_SENTINEL[0], y=_SENTINEL[1], z=_SENTINEL[2])]
        raw = serialize_message(m)
        if raw[:2] != CDR_LE:
            raise RuntimeError(f"unexpected CDR encapsulation {raw[:4]!r}")
        data = np.array(_SENTINEL, dtype="<f8").tobytes()
        at = raw.find(data)
        if at < 0 or raw.find(data, at + 1) >= 0:
            raise RuntimeError("cannot locate the points of a serialized Marker")
        one = struct.pack("<I", 1)
        if raw[at - 4:at] == one:  # the sequence length right before the first Point
            count_at = at - 4
        elif raw[at - 8:at - 4] == one and raw[at - 4:at] == bytes(4):  # then 4 bytes of alignment
            count_at = at - 8
        else:
            raise RuntimeError("cannot locate the point count of a serialized Marker")
        self._head = bytearray(raw[:at])
        self._count_at = count_at
        self._tail = bytes(raw[at + len(data):])
        # header.stamp is the message's first field: int32 sec, uint32 nanosec after the 4-byte encapsulation
        if raw[4:12] != bytes(8):
            raise RuntimeError("cannot locate the stamp of a serialized Marker")

    def encode(self, vertices: np.ndarray, stamp_ns: int = 0) -> bytes:
        """The serialized Marker with ``points`` = ``vertices`` (k, 3) and the stamp ``stamp_ns``."""
        v = np.ascontiguousarray(vertices, dtype="<f8")
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices must be (k, 3), got {v.shape}")
        head = self._head
        struct.pack_into("<iI", head, 4, int(stamp_ns // 1_000_000_000), int(stamp_ns % 1_000_000_000))
        struct.pack_into("<I", head, self._count_at, len(v))
        if not len(v):  # no element: no alignment before the (absent) first Point either
            return b"".join((head[:self._count_at + 4], self._tail))
        return b"".join((head, v.tobytes(), self._tail))
