"""
``sensor_msgs/JointState`` in and out as its serialized bytes (CDR), with numpy (no rclpy).

The estimator node subscribes to its measurements raw (rclpy ``raw=True``: the DDS sample's
bytes, no Python message object) and publishes its answers as serialized bytes: building and
converting rclpy message objects was most of what a plain rclpy node pays per message. This
module is the codec, checked against rclpy's own serialization (``test/test_cdr.py``).

The wire format is the one ROS 2 middlewares use for these types: a 4-byte encapsulation header
(``00 01 00 00``: plain CDR, little endian), then the fields in order, each aligned to its size
(at most 8) counted from the end of that header; padding bytes carry no meaning (they may hold
anything). A ``JointState`` is::

    header.stamp.sec int32, header.stamp.nanosec uint32, header.frame_id string,
    name string[], position float64[], velocity float64[], effort float64[]

with a string as ``uint32`` length (counting its NUL) + bytes + NUL, a sequence as ``uint32``
count + elements; an empty ``float64`` sequence has no padding after its count.

:class:`JointStateReader` decodes a batch of messages into arrays (one conversion per batch);
a message it cannot read (another encapsulation, a malformed or truncated one) is left to the
caller (the node deserializes it with rclpy and counts it). :class:`JointStateWriter` encodes
answers: the header of the measurement answered (its bytes, copied), the joint names (encoded
once) and up to three float64 arrays per message.
"""
from __future__ import annotations

from dataclasses import dataclass
import struct
from typing import List, Optional, Sequence, Tuple

import numpy as np

__all__ = ['ENCAPSULATION', 'JointStateReader', 'JointStateRun', 'JointStateWriter',
           'encode_float64', 'encode_names', 'header_bytes', 'parse_header', 'parse_joint_state']

#: plain CDR, little endian (the representation options are zero)
ENCAPSULATION = b'\x00\x01\x00\x00'
_BODY = 4                           # alignment is counted from here
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iII')       # sec, nanosec, frame_id length (with its NUL)
_F64 = struct.Struct('<d')
#: strings and sequences longer than this are malformed here (a JointState of a robot)
_MAX_COUNT = 1 << 20


def _align(offset: int, size: int) -> int:
    """Return ``offset`` (absolute) moved up to a multiple of ``size`` from the body's start."""
    return offset + (-(offset - _BODY) % size)


def encode_names(names: Sequence[str]) -> bytes:
    """
    Encode ``name`` (a string sequence) as it follows a 4-aligned offset: count and strings.

    The block's length depends only on the names; its padding only on the offset modulo 4, so
    one block serves every message (the header before it ends 4-aligned).
    """
    out = bytearray(_U32.pack(len(names)))
    for n in names:
        b = n.encode('utf-8') + b'\x00'
        out += b'\x00' * (-len(out) % 4)
        out += _U32.pack(len(b)) + b
    out += b'\x00' * (-len(out) % 4)       # the next field is a count (4-aligned)
    return bytes(out)


def header_bytes(sec: int, nanosec: int, frame_id: str) -> bytes:
    """Return a header's bytes as ``JointStateRun.headers`` holds them (stamp, frame_id)."""
    frame = frame_id.encode('utf-8') + b'\x00'
    return _STAMP.pack(sec, nanosec, len(frame)) + frame


def parse_header(header: bytes) -> Tuple[int, int, str]:
    """Inverse of :func:`header_bytes`: (sec, nanosec, frame_id)."""
    sec, nsec, n = _STAMP.unpack_from(header, 0)
    return sec, nsec, header[12:12 + n - 1].decode('utf-8')


def encode_float64(value: float) -> bytes:
    """Return a ``std_msgs/Float64`` message's bytes."""
    return ENCAPSULATION + _F64.pack(value)


def _read_string(raw: bytes, o: int) -> Tuple[str, int]:
    """Return (the string at ``o`` (4-aligned), the offset after it); ValueError if malformed."""
    (n,) = _U32.unpack_from(raw, o)
    o += 4
    if not 0 < n <= _MAX_COUNT or o + n > len(raw) or raw[o + n - 1] != 0:
        raise ValueError('malformed string')
    return raw[o:o + n - 1].decode('utf-8'), o + n


def _read_doubles(raw: bytes, o: int) -> Tuple[int, int, int]:
    """Return (count, data offset, offset after) of the float64 sequence whose count is at o."""
    o = _align(o, 4)
    (n,) = _U32.unpack_from(raw, o)
    o += 4
    if n == 0:
        return 0, o, o
    if n > _MAX_COUNT:
        raise ValueError('malformed sequence')
    o = _align(o, 8)
    end = o + 8 * n
    if end > len(raw):
        raise ValueError('truncated sequence')
    return n, o, end


def parse_joint_state(raw: bytes) -> Optional[tuple]:
    """
    Decode one JointState: (sec, nanosec, frame_id, names, position, velocity, effort).

    The arrays are float64 copies; None when the bytes are not a little-endian plain CDR
    JointState (another encapsulation, malformed, truncated). Trailing bytes are ignored (a
    serializer may leave some).
    """
    try:
        if raw[:2] != ENCAPSULATION[:2]:
            return None
        sec, nsec, flen = _STAMP.unpack_from(raw, _BODY)
        o = _BODY + 12
        if not 0 < flen <= _MAX_COUNT or o + flen > len(raw) or raw[o + flen - 1] != 0:
            return None
        frame = raw[o:o + flen - 1].decode('utf-8')
        o = _align(o + flen, 4)
        (count,) = _U32.unpack_from(raw, o)
        if count > _MAX_COUNT:
            return None
        o += 4
        names = []
        for _ in range(count):
            o = _align(o, 4)
            s, o = _read_string(raw, o)
            names.append(s)
        arrays = []
        for _ in range(3):
            n, at, o = _read_doubles(raw, o)
            arrays.append(np.frombuffer(raw, '<f8', n, at).astype(np.float64))
        return (sec, nsec, frame, names) + tuple(arrays)
    except (ValueError, struct.error, UnicodeDecodeError, IndexError):
        return None


@dataclass
class JointStateRun:
    """
    Consecutive messages of a batch with the same joint names and array lengths.

    start, stop : their indices in the batch (``stop`` excluded).
    sec, nanosec : (k,) int64 stamps; headers : each message's header bytes (stamp and
        frame_id, as received: what an answer echoes); names : the joint names (a tuple, the
        same object for every run with these names); position : (k, n) or None when the
        messages have none; velocity, effort : (k, m) float64 (m == 0: the messages have none);
        the arrays are read-only views of one buffer.
    """

    start: int
    stop: int
    sec: np.ndarray
    nanosec: np.ndarray
    headers: List[bytes]
    names: tuple
    position: Optional[np.ndarray]
    velocity: np.ndarray
    effort: np.ndarray


class JointStateReader:
    """
    Decode raw JointState messages in batches (module docstring).

    ``read(raws)`` returns the runs it decoded and the indices it could not (in order). The
    names block of the last few distinct name lists is kept, so the names of a driver's
    messages are compared as bytes, not decoded again.
    """

    #: distinct name lists remembered
    KEEP = 8

    def __init__(self):
        # names tuple -> (the block's pieces without its padding [(offset, bytes)], length)
        self._known: dict = {}
        self._last = None               # (names, the exact bytes of their last block)
        self._shapes: dict = {}         # (names, offset % 8) -> what _shape_of returns

    def _names(self, raw: bytes, o: int):
        """Return (names tuple, offset after the names) for the names block at ``o``."""
        for names, (pieces, length) in self._known.items():
            # the padding between the strings may hold anything: the rest is compared
            if all(raw.startswith(b, o + r) for r, b in pieces):
                return names, o + length
        (count,) = _U32.unpack_from(raw, o)
        if count > _MAX_COUNT:
            raise ValueError('malformed names')
        p = o + 4
        pieces = [(0, bytes(raw[o:p]))]
        out = []
        for _ in range(count):
            p = _align(p, 4)
            start = p
            s, p = _read_string(raw, p)
            pieces.append((start - o, bytes(raw[start:p])))
            out.append(s)
        names = tuple(out)
        if len(self._known) >= self.KEEP:
            self._known.pop(next(iter(self._known)))
        self._known[names] = (pieces, p - o)
        return names, p

    def _one(self, raw: bytes):
        """Return (sec, nsec, header end, names, (key, data offsets)) of one message."""
        if raw[:2] != b'\x00\x01':
            raise ValueError('not little-endian plain CDR')
        sec, nsec, flen = _STAMP.unpack_from(raw, _BODY)
        hend = _BODY + 12 + flen
        if not 0 < flen <= _MAX_COUNT or hend > len(raw) or raw[hend - 1] != 0:
            raise ValueError('malformed frame_id')
        raw[_BODY + 12:hend - 1].decode('utf-8')     # text, not only a length: else refused
        o = hend + (-hend % 4)
        last = self._last
        if last is not None and raw.startswith(last[1], o):   # the same bytes as the last one
            names, o = last[0], o + len(last[1])
        else:
            start = o
            names, o = self._names(raw, o)
            self._last = (names, bytes(raw[start:o]))
        # the arrays: where the last message of these names and this alignment had them
        shape = self._shapes.get((names, o % 8))
        if shape is not None and o + shape[3] <= len(raw) and \
                shape[0].unpack_from(raw, o) == shape[2]:
            return sec, nsec, hend, names, shape[4], [o + a for a in shape[1]]
        seqs, p = [], o
        for _ in range(3):
            n, a, p = _read_doubles(raw, p)
            seqs.append((n, a))
        key = (names,) + tuple(n for n, _ in seqs)
        if len(self._shapes) >= 4 * self.KEEP:          # a peer that keeps changing its names
            self._shapes.pop(next(iter(self._shapes)))
        self._shapes[(names, o % 8)] = _shape_of(o, seqs, p, key)
        return sec, nsec, hend, names, key, [a for n, a in seqs if n]

    def read(self, raws: Sequence[bytes]) -> Tuple[List[JointStateRun], List[int]]:
        """
        Decode ``raws``: (runs, the indices of the messages left undecoded).

        Runs and undecoded indices together cover the batch in order; a run ends where the
        names or the array lengths change or a message cannot be decoded.
        """
        runs: List[JointStateRun] = []
        bad: List[int] = []
        cur = None                  # (key, start, [(sec, nsec, hdr)], [chunks])
        for i, raw in enumerate(raws):
            try:
                sec, nsec, hend, names, key, data = self._one(raw)
            except (ValueError, struct.error, UnicodeDecodeError, IndexError, TypeError):
                if cur is not None:
                    runs.append(self._close(cur, i))
                    cur = None
                bad.append(i)
                continue
            if cur is None or cur[0] != key:
                if cur is not None:
                    runs.append(self._close(cur, i))
                cur = (key, i, [], [])
            cur[2].append((sec, nsec, raw[_BODY:hend]))
            chunks = cur[3]
            for a, n in zip(data, [n for n in key[1:] if n]):
                chunks.append(raw[a:a + 8 * n])
        if cur is not None:
            runs.append(self._close(cur, len(raws)))
        return runs, bad

    @staticmethod
    def _close(cur, stop: int) -> JointStateRun:
        (names, n_p, n_v, n_e), start, heads, chunks = cur
        k = len(heads)
        width = n_p + n_v + n_e
        # one conversion per run; read-only, little-endian float64 (the native type on the
        # platforms ROS 2 runs on; ``astype`` makes it so elsewhere)
        data = np.frombuffer(b''.join(chunks), '<f8').reshape(k, width) if width else \
            np.zeros((k, 0))
        if data.dtype != np.float64:
            data = data.astype(np.float64)
        stamps = np.array([(s, ns) for s, ns, _ in heads], dtype=np.int64).reshape(k, 2)
        return JointStateRun(start, stop, stamps[:, 0], stamps[:, 1], [h for _, _, h in heads],
                             names, data[:, :n_p] if n_p else None, data[:, n_p:n_p + n_v],
                             data[:, n_p + n_v:])


def _shape_of(o: int, seqs: list, end: int, key: tuple) -> tuple:
    """
    Return how to find the arrays of the next message like this one (names end at ``o``).

    (a struct reading the three counts at their offsets from ``o``, the data offsets from
    ``o`` of the non-empty arrays, the counts, the length the message needs from ``o``, key).
    """
    fmt, pos, at = '<', o, []
    for n, a in seqs:
        c = _align(pos, 4)
        fmt += f'{c - pos}xI' if c > pos else 'I'
        pos = c + 4
        if n:
            fmt += f'{a + 8 * n - pos}x'
            at.append(a - o)
            pos = a + 8 * n
    counts = tuple(n for n, _ in seqs)
    return struct.Struct(fmt), tuple(at), counts, end - o, key


class JointStateWriter:
    """
    Encode JointState messages: a header echoed, fixed names, and float64 arrays.

    ``names`` are encoded once. ``write(headers, position, velocity, effort)`` returns one
    ``bytes`` per header: ``headers`` are header bytes as :class:`JointStateRun` keeps them
    (stamp, frame_id); each array argument is (k, length) or None (an empty field). The bytes
    deserialize (rclpy) to the message ``JointState(header, name=names, position=...,
    velocity=..., effort=...)``.
    """

    def __init__(self, names: Sequence[str]):
        self.names = tuple(names)
        self._block = encode_names(self.names)
        self._layouts: dict = {}

    def _layout(self, parity: int, lengths: tuple) -> tuple:
        """Return the literal bytes around the arrays' data, for counts at ``parity`` (0/4)."""
        key = (parity, lengths)
        out = self._layouts.get(key)
        if out is None:
            lits, lit, off = [], b'', parity
            for n in lengths:
                lit += _U32.pack(n)
                off += 4
                if n:
                    if off % 8:
                        lit += b'\x00' * 4
                        off += 4
                    lits.append(lit)
                    lit = b''
                    off += 8 * n
            out = (tuple(lits), lit)
            self._layouts[key] = out
        return out

    def write(self, headers: Sequence[bytes], position=None, velocity=None,
              effort=None) -> List[bytes]:
        arrays = [a for a in (position, velocity, effort) if a is not None and a.shape[1]]
        lengths = tuple(0 if a is None else a.shape[1] for a in (position, velocity, effort))
        datas = [np.ascontiguousarray(a, dtype='<f8').tobytes() for a in arrays]
        widths = [8 * a.shape[1] for a in arrays]
        block, out = self._block, []
        for i, hdr in enumerate(headers):
            pad = -len(hdr) % 4
            # the first count's offset from the body's start, modulo 8
            parity = (len(hdr) + pad + len(block)) % 8
            lits, tail = self._layout(parity, lengths)
            parts = [ENCAPSULATION, hdr, b'\x00' * pad, block]
            for lit, data, w in zip(lits, datas, widths):
                parts.append(lit)
                parts.append(data[i * w:(i + 1) * w])
            parts.append(tail)
            out.append(b''.join(parts))
        return out
