"""The flight log written as the flight goes: a cut file's chunks stay readable, recover()
makes it a complete indexed file, sort_log() gives the same bytes whatever the arrival order."""

import random

import pytest
from mcap.reader import make_reader

from schemas.flightlog import FlightLogWriter, LogError, LogScan, log_is_complete, read_log, recover, scan, sort_log

P = "zp/0/"


def pwm(t, seq):
    return {"version": 1, "header": {"t_s": t, "seq": seq, "source": "motors"},
            "pwm_us": [1500.0 + seq % 7] * 4, "thrust_n": [2.0] * 4, "armed": True, "saturated": False,
            "imu_t_s": t}


def health(t, seq, source):
    return {"version": 1, "header": {"t_s": t, "seq": seq, "source": source}, "state": "running",
            "rate_hz": 100.0, "target_rate_hz": 100.0, "overruns": 0, "jitter_p99_ms": 0.1,
            "rejected": {}, "detail": ""}


def flight(n=600):
    """(key, message) rows of a short flight: pwm at 400 Hz, two services' health at 10 Hz."""
    rows = [(P + "motors/pwm", pwm(k / 400, k)) for k in range(n)]
    for source in ("attitude", "position"):
        rows += [(P + f"{source}/health", health(k / 10, k, source)) for k in range(n // 40)]
    return sorted(rows, key=lambda r: r[1]["header"]["t_s"])


def written_in_chunks(path, rows, per_chunk=100):
    """Write as the recorder does, a flush every `per_chunk` messages; returns the file's size
    after each flush (where a chunk ends)."""
    log = FlightLogWriter(path)
    ends = [path.stat().st_size]
    for i, (key, msg) in enumerate(rows, 1):
        assert log.write(key, msg)
        if i % per_chunk == 0:
            log.flush()
            ends.append(path.stat().st_size)
    log.close()
    return ends


def test_a_complete_log_reads_back_and_is_indexed(tmp_path):
    rows = flight()
    written_in_chunks(tmp_path / "f.mcap", rows)
    found = LogScan(tmp_path / "f.mcap")
    log = read_log(tmp_path / "f.mcap", found)
    assert found.complete and found.messages == len(rows) and log_is_complete(tmp_path / "f.mcap")
    assert log[P + "motors/pwm"] == [m for k, m in rows if k == P + "motors/pwm"]
    with open(tmp_path / "f.mcap", "rb") as fh:
        assert make_reader(fh).get_summary().statistics.message_count == len(rows)


def test_a_cut_log_gives_every_flushed_chunk_and_recovers_complete(tmp_path):
    rows = flight()
    ends = written_in_chunks(tmp_path / "f.mcap", rows, per_chunk=100)
    data = (tmp_path / "f.mcap").read_bytes()
    for chunks_done in (0, 1, 3):
        for extra in (0, 1, 9, 200):   # cut at the chunk's end, in the next record's header, in its data
            cut = tmp_path / f"cut-{chunks_done}-{extra}.mcap"
            cut.write_bytes(data[:ends[chunks_done] + extra])
            found = LogScan(cut)
            got = [(ch.topic, m.sequence) for ch, m in scan(cut, found)]
            assert got == [(k, m["header"]["seq"]) for k, m in rows[:100 * chunks_done]]
            assert not found.complete and found.chunks == chunks_done and not log_is_complete(cut)
            assert "cut" in found.describe()
            fixed = tmp_path / "fixed.mcap"
            assert recover(cut, fixed).messages == 100 * chunks_done
            with open(fixed, "rb") as fh:
                reader = make_reader(fh)
                assert reader.get_summary().statistics.message_count == 100 * chunks_done
                assert [(c.topic, m.sequence) for _, c, m in reader.iter_messages(log_time_order=False)] == got
            assert read_log(fixed) == read_log(cut)


def test_not_an_mcap_file_is_refused_with_its_name(tmp_path):
    for name, content in (("empty.mcap", b""), ("text.mcap", b"hello, not a log")):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(LogError, match=name):
            read_log(tmp_path / name)
        assert not log_is_complete(tmp_path / name)


def test_sorted_log_has_the_same_bytes_whatever_the_arrival_order(tmp_path):
    rows = flight()
    ready = (P + "@lockstep/sync/attitude", {"version": 1, "header": {"t_s": 0.0, "seq": 0, "source": "attitude"},
                                   "tick": -1, "next_tick": 0, "triggers": [], "period_ticks": 2})
    outputs = []
    for seed in (1, 2):
        arrived = rows + [ready] * 3   # a lockstep "ready", sent again until answered
        rng = random.Random(seed)
        # arrival order: each key in its own order (one sender each), the keys interleaved at random
        by_key: dict[str, list] = {}
        for row in arrived:
            by_key.setdefault(row[0], []).append(row)
        arrived = []
        while by_key:
            key = rng.choice(sorted(by_key))
            arrived.append(by_key[key].pop(0))
            if not by_key[key]:
                del by_key[key]
        written_in_chunks(tmp_path / f"stream{seed}.mcap", arrived, per_chunk=64)
        assert sort_log(tmp_path / f"stream{seed}.mcap", tmp_path / f"sorted{seed}.mcap") == len(rows) + 1
        outputs.append((tmp_path / f"sorted{seed}.mcap").read_bytes())
    assert outputs[0] == outputs[1]
    order = [(m.log_time, c.topic, m.sequence) for c, m in scan(tmp_path / "sorted1.mcap")]
    assert order == sorted(order) and len(set(order)) == len(order)


def test_sorting_a_cut_log_is_refused(tmp_path):
    ends = written_in_chunks(tmp_path / "f.mcap", flight(), per_chunk=100)
    (tmp_path / "cut.mcap").write_bytes((tmp_path / "f.mcap").read_bytes()[:ends[2]])
    with pytest.raises(LogError, match="recover"):
        sort_log(tmp_path / "cut.mcap", tmp_path / "sorted.mcap")


def test_the_fast_json_of_real_time_reads_back_the_same_values(tmp_path):
    """exact_json=False (the real-time recorder: msgspec's JSON) spells some numbers otherwise
    but every value reads back as written, to the bit: floats at the edges of their formats,
    the largest integers MessagePack carries, text beyond ASCII."""
    floats = [1e-7, 1e-05, 0.0001, 1e16, 1e22, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308,
              -0.0, 0.1, 1796420892.1423464, 8.534282042282904e-05, 123456789012345678.0]
    rng = random.Random(3)
    floats += [rng.uniform(-1, 1) * 10 ** rng.randrange(-30, 30) for _ in range(500)]
    rows = []
    for k in range(0, len(floats), 4):
        msg = pwm(k * 0.01, k)
        msg["pwm_us"] = (floats[k:k + 4] + [1.0] * 4)[:4]
        rows.append((P + "motors/pwm", msg))
    state = health(1.0, (1 << 64) - 1, "posição")
    state["rejected"] = {"malformed": (1 << 63) - 1, "ünknown": 0}
    rows.append((P + "attitude/health", state))
    log = FlightLogWriter(tmp_path / "f.mcap", exact_json=False)
    for key, msg in rows:
        assert log.write(key, msg)
    log.close()
    back = read_log(tmp_path / "f.mcap")
    assert back[P + "motors/pwm"] == [m for k, m in rows if k == P + "motors/pwm"]
    assert back[P + "attitude/health"] == [state]
    bits = [x.hex() for m in back[P + "motors/pwm"] for x in m["pwm_us"]]
    assert bits[:len(floats)] == [x.hex() for x in floats]   # -0.0 too, which == 0.0
