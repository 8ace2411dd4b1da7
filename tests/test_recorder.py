"""Recorder: what was published is in the MCAP after SIGTERM; a recording replays onto the bus."""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from services.recorder.recorder import RecorderError, RotatingRecorder
from shared import messages as m
from shared.codec import CodecError, decode, encode
from shared.recording import MessageDecoderFactory, McapWriter, Record, RecordingError, read_records, replay

REPO = Path(__file__).resolve().parents[1]
RAW_ENCODING = "text/plain"


def _messages(n: int) -> list[tuple[str, m.Message]]:
    """n messages of several models on several keys."""
    rng = np.random.default_rng(0)
    out: list[tuple[str, m.Message]] = []
    for i in range(n):
        kind = i % 4
        if kind == 0:
            out.append(("gd2p/test/push", m.PushRequest(object=m.ObjectRef(library_id=f"obj{i}"), direction_deg=float(i))))
        elif kind == 1:
            out.append(("gd2p/test/validate", m.ValidationJob(object=m.ObjectRef(library_id="box"), hand="allegro",
                                                               poses=rng.normal(size=(3, 25)).astype(np.float32), seed=i)))
        elif kind == 2:
            out.append(("gd2p/test/estop", m.EStop(reason=f"test {i}")))
        else:
            out.append(("gd2p/test/scale", m.ScaleReply(service="validator", count=i, started=[f"w{i}"])))
    return out


def _mcap_files(directory: Path) -> list[Path]:
    return sorted(directory.glob("gd2p-*.mcap"))


def _channels_and_schemas(path: Path):
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    return summary.channels, summary.schemas


# --- algorithm, no bus ---------------------------------------------------------------------------


def test_rotation_keeps_every_message_and_names_files(tmp_path):
    msgs = _messages(800)
    with RotatingRecorder(tmp_path, max_file_bytes=30_000) as rec:
        for i, (key, msg) in enumerate(msgs):
            rec.record(key, *encode(msg), log_time_ns=1_000 + i)
        rec.record("gd2p/test/raw", b"hello", RAW_ENCODING, log_time_ns=10_000)
    files = _mcap_files(tmp_path)
    assert len(files) >= 3, "a 30 kB limit must rotate"
    assert all(f.stat().st_size >= 30_000 for f in files[:-1]), "a file is closed only once full"
    assert files == rec.files
    assert not list(tmp_path.glob("*.part"))
    prefixes = {f.name.rsplit("-", 1)[0] for f in files}
    assert len(prefixes) == 1 and prefixes.pop().startswith("gd2p-") and files[0].name.endswith("-0000.mcap")
    records = [r for f in files for r in read_records(str(f))]
    assert [r.decode() for r in records[:-1]] == [msg for _, msg in msgs]
    assert [r.key for r in records[:-1]] == [key for key, _ in msgs]
    assert records[-1] == Record("gd2p/test/raw", RAW_ENCODING, b"hello", 10_000, 10_000)
    with pytest.raises(CodecError, match="unsupported encoding 'text/plain'"):
        records[-1].decode()


def test_schemas_and_raw_channels(tmp_path):
    path = tmp_path / "one.mcap"
    with McapWriter(str(path)) as w:
        w.write_message("gd2p/a", m.EStop(reason="x"))
        w.write_message("gd2p/a", m.EStop(reason="y"))
        w.write_message("gd2p/b", m.HealthQuery())
        w.write("gd2p/c", b"\x00\x01", "application/msgpack;NotAModelHere")
    channels, schemas = _channels_and_schemas(path)
    by_topic = {c.topic: c for c in channels.values()}
    assert set(by_topic) == {"gd2p/a", "gd2p/b", "gd2p/c"}  # one channel per key
    estop_schema = schemas[by_topic["gd2p/a"].schema_id]
    assert (estop_schema.name, estop_schema.encoding) == ("EStop", "jsonschema")
    assert "reason" in json.loads(estop_schema.data)["properties"]
    assert by_topic["gd2p/a"].message_encoding == "msgpack"
    assert by_topic["gd2p/c"].schema_id == 0  # unknown model: raw, no schema
    assert by_topic["gd2p/c"].metadata["zenoh_encoding"] == "application/msgpack;NotAModelHere"
    with open(path, "rb") as f:
        decoded = [msg for _, _, _, msg in make_reader(f, decoder_factories=[MessageDecoderFactory()]).iter_decoded_messages(topics=["gd2p/a"])]
    assert [d.reason for d in decoded] == ["x", "y"]


def test_bad_record_dir_and_size(tmp_path):
    (tmp_path / "file").write_text("not a dir")
    with pytest.raises(RecorderError, match="cannot create record directory"):
        RotatingRecorder(tmp_path / "file" / "sub")
    with pytest.raises(RecorderError, match="must be positive"):
        RotatingRecorder(tmp_path, max_file_bytes=0)


def test_unreadable_recording_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"definitely not mcap")
    with pytest.raises(RecordingError, match="not a readable MCAP file"):
        list(read_records(str(bad)))
    with pytest.raises(RecordingError, match="cannot open recording"):
        list(read_records(str(tmp_path / "missing.mcap")))


def test_replay_honours_timing_scaled_by_rate():
    records = [Record("k", b"", "x", t, t) for t in (0, 1_000_000_000, 3_000_000_000)]
    now = [100.0]
    sleeps: list[float] = []

    def sleep(s: float) -> None:
        sleeps.append(s)
        now[0] += s

    published: list[float] = []
    assert replay(iter(records), lambda r: published.append(now[0]), rate=2.0, clock=lambda: now[0], sleep=sleep) == 3
    assert published == pytest.approx([100.0, 100.5, 101.5])
    sleeps.clear()
    assert replay(iter(records), lambda r: None, rate=0, clock=lambda: now[0], sleep=sleep) == 3
    assert sleeps == []
    with pytest.raises(ValueError, match="rate must be >= 0"):
        replay(iter(records), lambda r: None, rate=-1)


# --- over the bus ------------------------------------------------------------------------------------


def _session(endpoint: str):
    from shared.bus import BusConfig, open_session

    return open_session(BusConfig(mode="client", connect=[endpoint], connect_timeout_ms=5000))


def _wait_for(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _token_alive(session, key: str) -> bool:
    return any(reply.ok is not None for reply in session.liveliness().get(key, timeout=1.0))


def test_recorder_process_records_everything_published_before_sigterm(zenoh_router, tmp_path):
    worker_id = "rec-test"
    cmd = [sys.executable, "-m", "services.recorder", "--connect", zenoh_router, "--record-dir", str(tmp_path),
           "--max-file-mb", "0.05", "--worker-id", worker_id]
    env = os.environ | {"PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        with _session(zenoh_router) as session:
            _wait_for(lambda: _token_alive(session, f"gd2p/alive/recorder/{worker_id}"), 30, "the recorder's liveliness token")
            msgs = _messages(400)
            publishers = {key: session.declare_publisher(key) for key in {k for k, _ in msgs} | {"gd2p/test/raw"}}
            _wait_for(lambda: all(p.matching_status.matching for p in publishers.values()), 10, "the recorder's subscription")
            for key, msg in msgs:
                payload, encoding = encode(msg)
                publishers[key].put(payload, encoding=encoding)
            publishers["gd2p/test/raw"].put(b"raw bytes", encoding=RAW_ENCODING)
            for p in publishers.values():
                p.undeclare()
            proc.send_signal(signal.SIGTERM)  # at once: the recorder must drain what is in flight
            output, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, output.decode(errors="replace")

    files = _mcap_files(tmp_path)
    assert len(files) >= 2, "0.05 MB files must rotate"
    assert not list(tmp_path.glob("*.part")), "every file is closed with its footer"
    records = [r for f in files for r in read_records(str(f)) if r.key.startswith("gd2p/test/")]
    recorded = [(r.key, r.decode()) for r in records if r.encoding != RAW_ENCODING]
    assert recorded == msgs  # all of them, in order, bit-exact
    assert [(r.key, r.payload) for r in records if r.encoding == RAW_ENCODING] == [("gd2p/test/raw", b"raw bytes")]
    assert all(r.log_time_ns > 0 for r in records)

    channels, schemas = _channels_and_schemas(files[0])
    topics = [c.topic for c in channels.values()]
    assert len(topics) == len(set(topics)), "one channel per key"
    names = {schemas[c.schema_id].name for c in channels.values() if c.topic.startswith("gd2p/test/") and c.schema_id}
    assert names == {"PushRequest", "ValidationJob", "EStop", "ScaleReply"}
    # The recorder is a worker like every other: its status heartbeat was recorded too.
    assert any(r.key == f"gd2p/status/recorder/{worker_id}" for f in files for r in read_records(str(f)))


def test_replay_republishes_a_recording(zenoh_router, tmp_path):
    from cli.recording import register

    path = tmp_path / "rec.mcap"
    msgs = _messages(12)
    with McapWriter(str(path)) as w:
        for i, (key, msg) in enumerate(msgs):
            w.write(key, *encode(msg), log_time_ns=1_000_000 * i)  # 1 ms apart
        w.write("gd2p/test/raw", b"raw", RAW_ENCODING, log_time_ns=20_000_000)
        w.write_message("gd2p/other/estop", m.EStop(reason="filtered out by --keys"), log_time_ns=30_000_000)

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["replay", str(path), "--rate", "2", "--connect", zenoh_router, "--keys", "gd2p/test/**"])

    received: list[tuple[str, bytes, str]] = []
    done = threading.Event()
    with _session(zenoh_router) as session:
        subscriber = session.declare_subscriber("gd2p/**")
        try:
            started = time.monotonic()
            assert args.func(args) == 0
            elapsed = time.monotonic() - started

            def collect() -> None:
                while len(received) < len(msgs) + 1:
                    sample = subscriber.handler.recv()
                    received.append((str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding)))
                done.set()

            threading.Thread(target=collect, daemon=True).start()
            assert done.wait(10), f"only {len(received)} of {len(msgs) + 1} samples arrived"
            time.sleep(0.3)
            assert subscriber.handler.try_recv() is None, "a sample outside --keys was replayed"
        finally:
            subscriber.undeclare()
    assert [(k, decode(p, e)) for k, p, e in received[:-1]] == msgs
    assert received[-1] == ("gd2p/test/raw", b"raw", RAW_ENCODING)
    assert elapsed >= 0.01 - 1e-3  # 20 ms of recording at rate 2


def test_replay_of_missing_file_fails_clearly(capsys):
    from cli.recording import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["replay", "/nonexistent/x.mcap"])
    assert args.func(args) == 2
    assert "no such recording: /nonexistent/x.mcap" in capsys.readouterr().err
