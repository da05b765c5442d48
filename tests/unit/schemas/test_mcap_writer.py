"""schemas.mcap_writer.McapWriter writes what mcap.writer.Writer writes, byte for byte (the
lockstep flight log must not change with the writer), and its files read back."""

import io
import random

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from schemas.mcap_writer import McapWriter


def script(seed: int, n: int):
    """Calls as the flight log makes them: schemas and channels registered as keys first come
    (mid-chunk too), messages of varied sizes and out-of-order times, flushes now and then,
    channels and a schema that never get a message."""
    rng = random.Random(seed)
    calls = [("schema", "never", "jsonschema", b"{}"), ("schema", "a", "jsonschema", b'{"type":"object"}'),
             ("channel", "t/never", "json", 1, {}), ("channel", "t/0", "json", 2, {"k": "v", "x": "yz"})]
    channels, schemas = 2, 2
    for i in range(n):
        r = rng.random()
        if r < 0.01:
            schemas += 1
            calls.append(("schema", f"s{schemas}", "protobuf", rng.randbytes(rng.randrange(0, 300))))
        elif r < 0.03:
            channels += 1
            calls.append(("channel", f"t/{channels}", rng.choice(["json", "protobuf"]), rng.randrange(1, schemas + 1), {}))
        elif r < 0.04:
            calls.append(("flush",))
        else:
            t = max(0, int(i * 2.5e6) + rng.randrange(-10**7, 10**7))
            calls.append(("message", rng.randrange(2, channels + 1), t, rng.randbytes(rng.randrange(0, 700)),
                          t + rng.randrange(0, 1000), rng.randrange(0, 1 << 32)))
    return calls


def play(writer, calls) -> None:
    writer.start(profile="", library="zenpilot")
    for call in calls:
        if call[0] == "schema":
            writer.register_schema(*call[1:])
        elif call[0] == "channel":
            writer.register_channel(*call[1:])
        elif call[0] == "message":
            writer.add_message(*call[1:])
        else:
            writer.flush()
    writer.finish()


@pytest.mark.parametrize("seed, n, chunk_size", [(1, 3000, 1 << 20), (2, 3000, 20_000), (3, 500, 1), (4, 0, 1 << 20)])
def test_same_bytes_as_the_mcap_library(seed, n, chunk_size):
    calls = script(seed, n)
    ours, theirs = io.BytesIO(), io.BytesIO()
    play(McapWriter(ours, chunk_size=chunk_size), calls)
    play(Writer(theirs, chunk_size=chunk_size, compression=CompressionType.ZSTD), calls)
    assert len(theirs.getvalue()) > 100
    assert ours.getvalue() == theirs.getvalue()


def test_a_faster_zstd_level_changes_the_bytes_not_the_messages():
    calls = script(5, 2000)
    fast, default = io.BytesIO(), io.BytesIO()
    play(McapWriter(fast, zstd_level=1), calls)
    play(McapWriter(default), calls)
    assert fast.getvalue() != default.getvalue()

    def messages(data):
        reader = make_reader(io.BytesIO(data))
        return [(c.topic, m.log_time, m.publish_time, m.sequence, m.data) for _, c, m in reader.iter_messages()]

    assert messages(fast.getvalue()) == messages(default.getvalue())
    assert len(messages(default.getvalue())) == sum(1 for c in calls if c[0] == "message")


def test_a_chunk_closes_past_chunk_size_not_at_it():
    """Records of 100 bytes and a chunk size of 1,000: the library closes a chunk at 1,100 bytes."""
    calls = [("schema", "a", "jsonschema", b"{}"), ("channel", "t", "json", 1, {}), ("message", 1, 0, b"", 0, 0),
             ("flush",)] + [("message", 1, k, bytes(69), k, k) for k in range(1, 40)]
    ours, theirs = io.BytesIO(), io.BytesIO()
    play(McapWriter(ours, chunk_size=1000), calls)
    play(Writer(theirs, chunk_size=1000, compression=CompressionType.ZSTD), calls)
    assert ours.getvalue() == theirs.getvalue()
    with io.BytesIO(theirs.getvalue()) as fh:
        assert make_reader(fh).get_summary().statistics.chunk_count == 5   # 1 + 11 + 11 + 11 + 6 messages
