"""The MCAP writer of the flight log: mcap.writer.Writer's output byte for byte, for the
options the log uses (ZSTD chunks, every index, statistics, summary offsets, CRCs), with a
cheaper path per message.

The library builds a dataclass per message, packs it field by field through a BytesIO and
appends a (time, offset) pair to a MessageIndex record object: ~9 us a message here, as much
as the recorder's JSON. Here a message is one struct.pack and two list appends; the message
indexes and statistics are packed once per chunk. Everything written once per file (header,
schemas, channels, chunk and summary records) still goes through mcap.records, so the
formats are the library's own. tests/unit/schemas/test_mcap_writer.py writes the same
records through both and compares the bytes.
"""

from __future__ import annotations

import struct
import zlib
from typing import BinaryIO

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Schema, Statistics,
                          SummaryOffset)
from mcap.writer import MCAP0_MAGIC

# opcode, record length, channel id, sequence, log time, publish time: a Message record up to its data
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_OPCODE = int(Opcode.MESSAGE)
_INDEX_HEAD = struct.Struct("<BQHI")   # a MessageIndex record up to its (time, offset) pairs
_INDEX_OPCODE = int(Opcode.MESSAGE_INDEX)
ZSTD_LEVEL = 3   # zstandard.compress's default, which mcap.writer.Writer uses


class McapWriter:
    """Writes an MCAP file to `stream` (a binary file open for writing) as
    mcap.writer.Writer(stream, chunk_size, CompressionType.ZSTD) does with its defaults.

    zstd_level: a lower one compresses each chunk faster into more bytes (still the same
    messages); only the default gives mcap.writer.Writer's bytes."""

    def __init__(self, stream: BinaryIO, chunk_size: int = 1024 * 1024, zstd_level: int = ZSTD_LEVEL):
        self._stream = stream
        self._chunk_size = chunk_size
        self._compressor = zstandard.ZstdCompressor(level=zstd_level)
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        # the chunk in progress: its records' bytes, their length, and per channel (in order of
        # first message) the flat [time, offset, time, offset, ...] of its message index
        self._chunk: list[bytes] = []
        self._chunk_len = 0
        self._chunk_messages = 0
        self._index: dict[int, list[int]] = {}
        # statistics: per channel (in order of first message) its count; the file's times
        self._counts: dict[int, int] = {}
        self._message_count = 0
        self._start_time = 0
        self._end_time = 0

    def start(self, profile: str = "", library: str = "") -> None:
        self._stream.write(MCAP0_MAGIC)
        self._write_records(Header(profile, library))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, data=data, encoding=encoding, name=name)
        self._schemas.append(schema)
        self._add_to_chunk(schema)
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str] | None = None) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic, message_encoding=message_encoding,
                          schema_id=schema_id, metadata=dict(metadata or {}))
        self._channels.append(channel)
        self._add_to_chunk(channel)
        return channel.id

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        offset = self._chunk_len
        head = _MESSAGE_HEAD.pack(_MESSAGE_OPCODE, 22 + len(data), channel_id, sequence, log_time, publish_time)
        chunk = self._chunk
        chunk.append(head)
        chunk.append(data)
        index = self._index.get(channel_id)
        if index is None:
            index = self._index[channel_id] = []
        index.append(log_time)
        index.append(offset)
        self._chunk_messages += 1
        self._chunk_len = offset + 31 + len(data)
        if self._chunk_len > self._chunk_size:
            self._finish_chunk()

    def flush(self) -> None:
        """Close the chunk in progress (if it holds a message) and hand the file's bytes to the OS."""
        self._finish_chunk()
        self._stream.flush()

    def finish(self) -> None:
        """The last chunk, the data end and the summary: the file is complete (not closed)."""
        self._finish_chunk()
        self._write_records(DataEnd(0))
        stream = self._stream
        summary_start = stream.tell()
        summary = RecordBuilder()
        offsets = []

        def group(opcode: Opcode, records) -> None:
            start = summary.count
            for record in records:
                record.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                         group_length=summary.count - start))

        group(Opcode.SCHEMA, self._schemas)
        group(Opcode.CHANNEL, self._channels)
        group(Opcode.STATISTICS, [Statistics(
            attachment_count=0, channel_count=len(self._channels), channel_message_counts=self._counts,
            chunk_count=len(self._chunk_indexes), message_count=self._message_count,
            message_end_time=self._end_time, message_start_time=self._start_time, metadata_count=0,
            schema_count=len(self._schemas))])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, [])
        group(Opcode.METADATA_INDEX, [])
        summary_offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        data = summary.end()
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start if data else 0,
                                     summary_offset_start), zlib.crc32(data))
        stream.write(data)
        self._write_records(Footer(summary_start=summary_start if data else 0,
                                   summary_offset_start=summary_offset_start, summary_crc=crc))
        stream.write(MCAP0_MAGIC)

    # -------------------------------------------------------------------------
    def _write_records(self, *records) -> None:
        builder = RecordBuilder()
        for record in records:
            record.write(builder)
        self._stream.write(builder.end())

    def _add_to_chunk(self, record) -> None:
        builder = RecordBuilder()
        record.write(builder)
        data = builder.end()
        self._chunk.append(data)
        self._chunk_len += len(data)
        if self._chunk_len > self._chunk_size:
            self._finish_chunk()

    def _finish_chunk(self) -> None:
        if not self._chunk_messages:   # as the library: schemas and channels wait for a message
            return
        data = b"".join(self._chunk)
        index = self._index
        times = [t for pairs in index.values() for t in pairs[::2]]
        start, end = min(times), max(0, *times)
        counts = self._counts
        for channel_id, pairs in index.items():
            counts[channel_id] = counts.get(channel_id, 0) + len(pairs) // 2
        if self._message_count == 0:
            self._start_time = start
        else:
            self._start_time = min(self._start_time, start)
        self._end_time = max(self._end_time, end)
        self._message_count += self._chunk_messages
        compressed = self._compressor.compress(data)
        stream = self._stream
        chunk_start = stream.tell()
        builder = RecordBuilder()
        Chunk(compression="zstd", data=compressed, message_start_time=start, message_end_time=end,
              uncompressed_crc=zlib.crc32(data), uncompressed_size=len(data)).write(builder)
        chunk_length = builder.count
        stream.write(builder.end())
        index_start = chunk_start + chunk_length
        offsets = {}
        records = []
        position = 0
        for channel_id, pairs in index.items():
            offsets[channel_id] = index_start + position
            record = _INDEX_HEAD.pack(_INDEX_OPCODE, 6 + 8 * len(pairs), channel_id, 8 * len(pairs)) + \
                struct.pack(f"<{len(pairs)}Q", *pairs)
            records.append(record)
            position += len(record)
        stream.write(b"".join(records))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_start,
            chunk_length=chunk_length, message_index_offsets=offsets, message_index_length=position,
            compression="zstd", compressed_size=len(compressed), uncompressed_size=len(data)))
        self._chunk = []
        self._chunk_len = 0
        self._chunk_messages = 0
        self._index = {}
