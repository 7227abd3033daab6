"""Foxglove's ``foxglove.FrameTransforms`` in the protobuf wire format, without
the protobuf library.

A recording stores each whole-body pose's transforms (``body/tf``) in the
encoding Foxglove reads natively for its well-known schemas: protobuf, the
schema being a ``FileDescriptorSet`` of Foxglove's ``.proto`` files (the
descriptors are written here by hand, the same messages, fields and numbers
as Foxglove's own, which ``tests/test_recorder_writes.py`` checks against
``foxglove-schemas-protobuf``). The wire format is what makes them cheap:
every number is an 8-byte double at a fixed place, so the messages of many
poses are one array fill (``body_tree.Transforms``); only the time stamp is
a varint, of a few bytes.

Strategy: the few records needed are spelled out with :func:`field` and
:func:`varint`; nothing reads protobuf here.
"""

from __future__ import annotations

import functools

#: The schema name Foxglove knows the message by, and its encodings in MCAP.
SCHEMA_NAME = "foxglove.FrameTransforms"
SCHEMA_ENCODING = "protobuf"
MESSAGE_ENCODING = "protobuf"

# wire types
_VARINT, _LEN = 0, 2
# FieldDescriptorProto's label and type enums
_OPTIONAL, _REPEATED = 1, 3
_DOUBLE, _INT64, _INT32, _STRING, _MESSAGE = 1, 3, 5, 9, 11


def varint(n: int) -> bytes:
    """``n`` (0 or more) as a protobuf varint."""
    if n < 0:
        raise ValueError(f"a varint here is not negative: {n}")
    out = bytearray()
    while n > 0x7F:
        out.append(n & 0x7F | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def field(number: int, value: int | bytes | str) -> bytes:
    """One field: an integer as a varint, bytes or text length-delimited."""
    if isinstance(value, int):
        return varint(number << 3 | _VARINT) + varint(value)
    data = value.encode() if isinstance(value, str) else value
    return varint(number << 3 | _LEN) + varint(len(data)) + data


def timestamp(t_ns: int) -> bytes:
    """A ``google.protobuf.Timestamp`` (seconds, nanos) of ``t_ns`` (0 or more),
    both fields written even where 0."""
    sec, nsec = divmod(t_ns, 1_000_000_000)
    return _seconds(sec) + _nanos(nsec)


@functools.lru_cache(maxsize=4)  # a recording's seconds change once a second
def _seconds(sec: int) -> bytes:
    return b"\x08" + varint(sec)


def _nanos(n: int) -> bytes:
    # varint, unrolled: on the recorder's path once a pose
    if n < 0x80:
        return bytes((0x10, n))
    if n < 0x4000:
        return bytes((0x10, n & 0x7F | 0x80, n >> 7))
    if n < 0x200000:
        return bytes((0x10, n & 0x7F | 0x80, n >> 7 & 0x7F | 0x80, n >> 14))
    if n < 0x10000000:
        return bytes((0x10, n & 0x7F | 0x80, n >> 7 & 0x7F | 0x80, n >> 14 & 0x7F | 0x80,
                      n >> 21))  # fmt: skip
    return b"\x10" + varint(n)


def _field_proto(name: str, number: int, kind: int, type_name: str = "",
                 label: int = _OPTIONAL) -> bytes:  # fmt: skip
    # FieldDescriptorProto: name 1, number 3, label 4, type 5, type_name 6, json_name 10
    json_name = name.split("_", maxsplit=1)[0] + "".join(p.title() for p in name.split("_")[1:])
    return (field(1, name) + field(3, number) + field(4, label) + field(5, kind)
            + (field(6, type_name) if type_name else b"") + field(10, json_name))  # fmt: skip


def _message_proto(name: str, *fields: bytes) -> bytes:
    # DescriptorProto: name 1, field 2
    return field(1, name) + b"".join(field(2, f) for f in fields)


def _file_proto(name: str, package: str, dependencies: list[str], *messages: bytes) -> bytes:
    # FileDescriptorProto: name 1, package 2, dependency 3, message_type 4, syntax 12
    return (field(1, name) + field(2, package) + b"".join(field(3, d) for d in dependencies)
            + b"".join(field(4, m) for m in messages) + field(12, "proto3"))  # fmt: skip


def _descriptor_set() -> bytes:
    xyz = [_field_proto(a, i + 1, _DOUBLE) for i, a in enumerate("xyz")]
    files = [
        _file_proto("google/protobuf/timestamp.proto", "google.protobuf", [],
                    _message_proto("Timestamp", _field_proto("seconds", 1, _INT64),
                                   _field_proto("nanos", 2, _INT32))),
        _file_proto("foxglove/Vector3.proto", "foxglove", [], _message_proto("Vector3", *xyz)),
        _file_proto("foxglove/Quaternion.proto", "foxglove", [],
                    _message_proto("Quaternion", *xyz, _field_proto("w", 4, _DOUBLE))),
        _file_proto("foxglove/FrameTransform.proto", "foxglove",
                    ["foxglove/Quaternion.proto", "foxglove/Vector3.proto",
                     "google/protobuf/timestamp.proto"],
                    _message_proto(
                        "FrameTransform",
                        _field_proto("timestamp", 1, _MESSAGE, ".google.protobuf.Timestamp"),
                        _field_proto("parent_frame_id", 2, _STRING),
                        _field_proto("child_frame_id", 3, _STRING),
                        _field_proto("translation", 4, _MESSAGE, ".foxglove.Vector3"),
                        _field_proto("rotation", 5, _MESSAGE, ".foxglove.Quaternion"))),
        _file_proto("foxglove/FrameTransforms.proto", "foxglove", ["foxglove/FrameTransform.proto"],
                    _message_proto("FrameTransforms",
                                   _field_proto("transforms", 1, _MESSAGE,
                                                ".foxglove.FrameTransform", _REPEATED))),
    ]  # fmt: skip
    # FileDescriptorSet: file 1, dependencies before what depends on them
    return b"".join(field(1, f) for f in files)


#: The schema data of ``foxglove.FrameTransforms`` (a ``FileDescriptorSet``).
FRAME_TRANSFORMS_DESCRIPTOR = _descriptor_set()

#: ``foxglove.FrameTransforms`` with no transforms: the empty message.
NO_TRANSFORMS = b""


def transform_layout(parent: str, child: str, stamp_len: int) -> tuple[bytes, int, list[int]]:
    """One ``FrameTransform`` inside ``FrameTransforms`` (field 1), its stamp
    ``stamp_len`` bytes long: the record with zeros for the stamp and the seven
    numbers (translation x, y, z, rotation x, y, z, w: doubles of 8 bytes,
    little-endian), the stamp's offset in it and the offsets of the numbers."""
    xyz = b"".join(bytes([i << 3 | 1]) + bytes(8) for i in (1, 2, 3))  # fixed64 fields 1-3
    translation = field(4, xyz)
    rotation = field(5, xyz + bytes([4 << 3 | 1]) + bytes(8))
    stamp = field(1, bytes(stamp_len))
    body = stamp + field(2, parent) + field(3, child) + translation + rotation
    head = varint(1 << 3 | _LEN) + varint(len(body))
    stamp_at = len(head) + len(stamp) - stamp_len
    at = len(head) + len(body) - len(rotation) - len(translation)
    # after each message's tag and length, each number after its one-byte tag
    numbers = [at + 3 + 9 * i for i in range(3)] + [at + len(translation) + 3 + 9 * i
                                                    for i in range(4)]  # fmt: skip
    return head + body, stamp_at, numbers
