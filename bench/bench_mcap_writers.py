"""The two MCAP writers ``export-mcap`` could use, side by side on the same messages.

Usage: ``python bench/bench_mcap_writers.py [--frames N] [--repeats R] [--detections]``.

A ``room`` recording is simulated (images by default), run through the pipeline and exported with
``tagtrail export-mcap`` (the ``mcap`` library). Every message of that file (topic, schema,
channel metadata, log time, CDR bytes) is then written again, from memory, by (a) the ``mcap``
library as ``export-mcap`` writes (zstd chunks, profile ``ros2``) and (b) ``foxglove-sdk``'s
``open_mcap`` (zstd, profile ``ros2``, one ``Channel`` per topic with a ``ros2msg`` schema and
``cdr`` encoding). Printed: the export command's own time, each writer's write time (median of
R, the writers interleaved so that both see the same load) and size, and what each file gives
back to the ``mcap`` reader (decoding every message with ``mcap_ros2``) and to rosbags (a bare
``.mcap`` file, every message deserialized): header, schemas, channel metadata, log and publish
times, sequence numbers, payload bytes, compared with the input.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.cli_helpers import ROOM_QUERY_PIPELINE as PIPELINE  # noqa: E402


class Msg(NamedTuple):
    topic: str
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


class Content(NamedTuple):
    profile: str
    library: str
    schemas: dict[str, tuple[str, str, bytes]]  # topic → (name, encoding, data)
    metadata: dict[str, dict[str, str]]  # topic → channel metadata
    messages: list[Msg]


def read(path: Path) -> Content:
    """Everything a reader gets back, every message decoded by ``mcap_ros2`` on the way."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with path.open("rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        head = r.get_header()
        summary = r.get_summary()
        assert summary is not None
        schemas = {
            c.topic: (
                summary.schemas[c.schema_id].name,
                summary.schemas[c.schema_id].encoding,
                bytes(summary.schemas[c.schema_id].data),
            )
            for c in summary.channels.values()
        }
        meta = {c.topic: dict(c.metadata) for c in summary.channels.values()}
        msgs = [
            Msg(ch.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data))
            for _, ch, m, _ in r.iter_decoded_messages(log_time_order=True)
        ]
    return Content(head.profile, head.library, schemas, meta, msgs)


def rosbags_read(path: Path) -> list[tuple[str, int, bytes]]:
    """``(topic, log time, CDR)`` as rosbags reads the bare file, each message deserialized with
    the definitions the file stores."""
    from rosbags.highlevel import AnyReader

    out = []
    with AnyReader([path]) as r:
        for conn, t, raw in r.messages():
            r.deserialize(raw, conn.msgtype)
            out.append((conn.topic, t, bytes(raw)))
    return out


def write_mcap_lib(c: Content, out: Path) -> None:
    """As ``export-mcap`` writes (``commands/export_mcap.py``: ``Channels``)."""
    from mcap.writer import CompressionType, Writer

    with out.open("wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="tagtrail export-mcap")
        sid: dict[str, int] = {}
        cid: dict[str, int] = {}
        for topic, (name, enc, data) in c.schemas.items():
            if name not in sid:
                sid[name] = w.register_schema(name=name, encoding=enc, data=data)
            cid[topic] = w.register_channel(
                topic=topic, message_encoding="cdr", schema_id=sid[name], metadata=c.metadata[topic]
            )
        for m in c.messages:
            w.add_message(
                channel_id=cid[m.topic],
                log_time=m.log_time,
                publish_time=m.publish_time,
                sequence=m.sequence,
                data=m.data,
            )
        w.finish()


def write_sdk(c: Content, out: Path) -> None:
    """``foxglove.open_mcap`` with a private context, one channel per topic."""
    import foxglove
    from foxglove.mcap import MCAPWriteOptions

    ctx = foxglove.Context()
    with foxglove.open_mcap(
        out, context=ctx, allow_overwrite=True, writer_options=MCAPWriteOptions(profile="ros2")
    ):
        ch: dict[str, Any] = {}
        for topic, (name, enc, data) in c.schemas.items():
            ch[topic] = foxglove.Channel(
                topic,
                schema=foxglove.Schema(name=name, encoding=enc, data=data),
                message_encoding="cdr",
                metadata=c.metadata[topic],
                context=ctx,
            )
        for m in c.messages:
            ch[m.topic].log(m.data, log_time=m.log_time)
        for x in ch.values():
            x.close()


def compare(ref: Content, got: Content) -> list[str]:
    """What ``got`` does not give back of ``ref`` (empty: everything)."""
    diffs = []
    if got.profile != ref.profile:
        diffs.append(f"profile {got.profile!r}")
    if got.schemas != ref.schemas:
        diffs.append("schemas differ")
    if got.metadata != ref.metadata:
        diffs.append("channel metadata differs")
    key = [(m.topic, m.log_time, m.data) for m in ref.messages]
    if sorted(key) != sorted((m.topic, m.log_time, m.data) for m in got.messages):
        diffs.append("messages (topic, log time, bytes) differ")
    if [m.publish_time for m in got.messages] != [m.log_time for m in got.messages]:
        diffs.append("publish time != log time")
    first = {}
    for m in got.messages:
        first.setdefault(m.topic, m.sequence)
    if set(first.values()) != {0}:
        diffs.append(f"sequence starts at {sorted(set(first.values()))} (export-mcap: 0)")
    return diffs


def main() -> None:
    import tagtrail.cli
    from tagtrail.sim import simulate

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--detections", action="store_true", help="a detections bag, no images")
    a = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_mcap_") as d:
        root = Path(d)
        simulate(
            "room",
            root / "bags",
            frames=a.frames,
            query_frames=max(5, a.frames // 4),
            detections=a.detections,
        )
        (root / "pipeline.yaml").write_text(PIPELINE)
        pipe = str(root / "pipeline.yaml")
        assert tagtrail.cli.main(["run", "-p", pipe]) == 0
        exported = root / "query_1.mcap"
        t0 = time.perf_counter()
        assert (
            tagtrail.cli.main(
                ["export-mcap", "-p", pipe, "--dataset", "query_1", "-o", str(exported)]
            )
            == 0
        )
        t_export = time.perf_counter() - t0
        content = read(exported)
        n, payload = len(content.messages), sum(len(m.data) for m in content.messages)
        print(
            f"\n{n} messages on {len(content.schemas)} topics, {payload / 1e6:.2f} MB of CDR; "
            f"the whole export-mcap command: {t_export:.2f} s"
        )
        writers = {
            "mcap library (export-mcap)": write_mcap_lib,
            "foxglove-sdk open_mcap": write_sdk,
        }
        times: dict[str, list[float]] = {name: [] for name in writers}
        for _ in range(a.repeats):  # interleaved: both writers see the same machine load
            for name, fn in writers.items():
                out = root / f"{fn.__name__}.mcap"
                out.unlink(missing_ok=True)
                t0 = time.perf_counter()
                fn(content, out)
                times[name].append(time.perf_counter() - t0)
        print(f"{'writer':<26}{'write ms':>10}{'size MB':>10}  readers")
        for name, fn in writers.items():
            out = root / f"{fn.__name__}.mcap"
            got = read(out)
            bags = rosbags_read(out)
            ok_bags = sorted(bags) == sorted(
                (m.topic, m.log_time, m.data) for m in content.messages
            )
            diffs = compare(content, got) + ([] if ok_bags else ["rosbags reads other messages"])
            print(
                f"{name:<26}{statistics.median(times[name]) * 1e3:>10.1f}"
                f"{out.stat().st_size / 1e6:>10.3f}  mcap+mcap_ros2 and rosbags decode all; "
                f"{'; '.join(diffs) or 'identical content'} (library {got.library!r})"
            )


if __name__ == "__main__":
    main()
