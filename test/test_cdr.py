"""dgp_ros.msgs.cdr: the JointState codec of the node's raw path, against rclpy's serialization."""
import math
import random
import struct

import numpy as np
import pytest

from dgp_ros.msgs.cdr import (encode_float64, encode_names, JointStateReader, JointStateWriter,
                              parse_joint_state)

serialization = pytest.importorskip('rclpy.serialization')
JointState = pytest.importorskip('sensor_msgs.msg').JointState

ALPHABET = 'abcdefghijklmnopqrstuvwxyz_0123456789/é'


def _name(rng, n_max=24) -> str:
    return ''.join(rng.choice(ALPHABET) for _ in range(rng.randint(0, n_max)))


def _message(rng, names=None, lengths=None) -> JointState:
    """Return a random JointState: names and frame ids of all lengths (alignment), any arrays."""
    m = JointState()
    m.header.stamp.sec = rng.randint(-2**31, 2**31 - 1)
    m.header.stamp.nanosec = rng.randint(0, 2**32 - 1)
    m.header.frame_id = _name(rng, 13)
    if names is None:
        names = list(dict.fromkeys(_name(rng) for _ in range(rng.randint(0, 9))))
    m.name = list(names)
    nrng = np.random.default_rng(rng.randint(0, 2**31))
    for field, n in zip(('position', 'velocity', 'effort'),
                        lengths or [rng.choice([0, len(names), rng.randint(0, 9)])
                                    for _ in range(3)]):
        x = nrng.standard_normal(n) * 10.0 ** nrng.integers(-5, 6, n)
        if n and rng.random() < 0.1:
            x[rng.randrange(n)] = rng.choice([math.nan, math.inf, -math.inf, 0.0, -0.0])
        setattr(m, field, x.tolist())
    return m


def _same(a, b) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))


def _check_run_row(run, j, m) -> None:
    assert run.sec[j] == m.header.stamp.sec and run.nanosec[j] == m.header.stamp.nanosec
    assert run.names == tuple(m.name)
    pos = np.zeros(0) if run.position is None else run.position[j]
    for got, want in ((pos, m.position), (run.velocity[j], m.velocity),
                      (run.effort[j], m.effort)):
        assert _same(got, want)


def test_parse_matches_rclpy_on_random_messages():
    rng = random.Random(0)
    for _ in range(600):
        m = _message(rng)
        raw = serialization.serialize_message(m)
        sec, nsec, frame, names, p, v, e = parse_joint_state(raw)
        assert (sec, nsec, frame, names) == (m.header.stamp.sec, m.header.stamp.nanosec,
                                             m.header.frame_id, list(m.name))
        assert _same(p, m.position) and _same(v, m.velocity) and _same(e, m.effort)


def test_reader_batches_match_rclpy_and_split_where_the_shape_changes():
    rng = random.Random(1)
    for _ in range(150):
        # a driver's stream (fixed names and lengths) with odd messages mixed in
        names = [_name(rng) for _ in range(rng.randint(1, 8))]
        names = list(dict.fromkeys(names))
        lengths = [rng.choice([0, len(names)]), len(names), len(names)]
        msgs = [_message(rng, names, lengths) if rng.random() < 0.8 else _message(rng)
                for _ in range(rng.randint(1, 20))]
        raws = [serialization.serialize_message(m) for m in msgs]
        reader = JointStateReader()
        runs, bad = reader.read(raws)
        assert bad == []
        seen = []
        for run in runs:
            assert run.stop > run.start
            seen += list(range(run.start, run.stop))
            for j, i in enumerate(range(run.start, run.stop)):
                _check_run_row(run, j, msgs[i])
                # the header echoed: the message's own stamp and frame_id bytes
                assert run.headers[j] == raws[i][4:4 + 12 + len(
                    msgs[i].header.frame_id.encode()) + 1]
        assert seen == list(range(len(msgs)))
        # a run holds messages of one shape: consecutive runs differ
        for a, b in zip(runs, runs[1:]):
            shape = lambda r: (r.names, None if r.position is None else r.position.shape[1],  # noqa
                               r.velocity.shape[1], r.effort.shape[1])
            assert shape(a) != shape(b)


def test_reader_keeps_names_as_one_object_and_ignores_padding_bytes():
    names = ['panda_joint1', 'j', 'abc']          # 13, 2 and 4 bytes: padding between them
    m = _message(random.Random(2), names, [3, 3, 3])
    raw = bytearray(serialization.serialize_message(m))
    reader = JointStateReader()
    r1, _ = reader.read([bytes(raw)])
    # scribble over the padding after 'panda_joint1\0' (offset of the names block + 4 + 4 + 13)
    o = 4 + 12 + len(m.header.frame_id.encode()) + 1
    o += -(o - 4) % 4
    pad = o + 4 + 4 + 13
    raw[pad:pad + 3] = b'\xff\xfe\xfd'
    r2, bad = reader.read([bytes(raw)])
    assert bad == [] and r2[0].names is r1[0].names
    _check_run_row(r2[0], 0, m)


def test_reader_leaves_what_it_cannot_read_to_the_caller():
    rng = random.Random(3)
    m = _message(rng, ['a', 'b'], [2, 2, 2])
    good = serialization.serialize_message(m)
    big_endian = b'\x00\x00' + good[2:]
    truncated = good[:len(good) - 12]
    o = 4 + 12 + len(m.header.frame_id.encode()) + 1
    o += -(o - 4) % 4                                   # the names' count
    cases = [b'', b'\x00\x01\x00\x00', big_endian, truncated, good[:20],
             good[:o] + struct.pack('<I', 10 ** 9) + good[o + 4:]]
    for _ in range(200):            # random bytes, and random damage to a good message
        k = rng.randrange(len(good))
        cases.append(good[:k] + bytes([rng.randrange(256)]) + good[k + 1:])
        cases.append(bytes(rng.randrange(256) for _ in range(rng.randrange(64))))
    reader = JointStateReader()
    runs, bad = reader.read(cases + [good])
    assert {0, 1, 2, 3, 4, 5} <= set(bad)
    decoded = {i for r in runs for i in range(r.start, r.stop)}
    assert decoded | set(bad) == set(range(len(cases) + 1)) and not decoded & set(bad)
    assert len(cases) in decoded
    for i in decoded:               # whatever it did decode, rclpy reads the same way
        try:
            m = serialization.deserialize_message(cases[i] if i < len(cases) else good,
                                                  JointState)
        except Exception:           # noqa: BLE001 - damage rclpy refuses: nothing to compare
            continue
        run = next(r for r in runs if r.start <= i < r.stop)
        if tuple(m.name) == run.names:
            _check_run_row(run, i - run.start, m)
    for raw in cases[:6]:
        assert parse_joint_state(raw) is None


def test_writer_output_is_what_rclpy_reads():
    rng = random.Random(4)
    for _ in range(300):
        names = list(dict.fromkeys(_name(rng) for _ in range(rng.randint(0, 9))))
        src = [_message(rng, names, [0, len(names), len(names)]) for _ in range(rng.randint(1, 6))]
        raws = [serialization.serialize_message(m) for m in src]
        runs, _ = JointStateReader().read(raws)
        headers = [h for r in runs for h in r.headers]
        k = len(src)
        nrng = np.random.default_rng(rng.randint(0, 2**31))
        widths = [rng.choice([0, len(names), rng.randint(0, 50)]) for _ in range(3)]
        arrays = [None if w == 0 and rng.random() < 0.5 else nrng.standard_normal((k, w))
                  for w in widths]
        out = JointStateWriter(names).write(headers, *arrays)
        assert len(out) == k
        for i, b in enumerate(out):
            m = serialization.deserialize_message(b, JointState)
            assert m.header.stamp.sec == src[i].header.stamp.sec
            assert m.header.stamp.nanosec == src[i].header.stamp.nanosec
            assert m.header.frame_id == src[i].header.frame_id
            assert list(m.name) == names
            for got, a in zip((m.position, m.velocity, m.effort), arrays):
                assert _same(got, np.zeros(0) if a is None else a[i])
            # and rclpy writes the same bytes, up to its padding and trailing bytes
            ref = serialization.serialize_message(m)
            assert parse_joint_state(ref)[3:4] == parse_joint_state(b)[3:4]
            assert len(b) <= len(ref)


def test_names_block_and_float64():
    from std_msgs.msg import Float64
    for x in (0.0, -1.5, 1e300, math.inf):
        assert serialization.deserialize_message(encode_float64(x), Float64).data == x
    assert encode_names([]) == b'\x00' * 4
    assert len(encode_names(['ab', 'c'])) % 4 == 0


def test_a_peer_that_keeps_changing_its_names_does_not_grow_the_reader():
    import gc
    import tracemalloc
    rng = random.Random(5)
    raws = [serialization.serialize_message(_message(rng, [f'joint_{i}_{k}' for k in range(3)],
                                                     [3, 3, 3])) for i in range(1200)]
    reader = JointStateReader()
    tracemalloc.start()
    try:
        for raw in raws[:200]:
            reader.read([raw])
        gc.collect()                # a full collection empties the tuple free lists, which
        early = tracemalloc.get_traced_memory()[0]      # tracemalloc counts as held
        for raw in raws[200:]:
            reader.read([raw])
        gc.collect()
        late = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert late - early < 20_000, (early, late)         # bytes: 1000 more name lists held none
