"""Which recording holds a trigger: the MCAP file, and the time range of its messages.

Every message of one trigger is logged at the trigger's time (see
:mod:`service.recorder`), so a result is found by its ``triggered_ns``: a
finished file answers through its index (summary statistics first, then the
``/result`` messages at that time); the file still being written is read
from its start, unpacking only the chunks whose time range holds the trigger.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import breakup_chunk, make_reader
from mcap.records import Channel, Chunk, Message
from mcap.stream_reader import StreamReader

from .recorder import is_finished, iter_records

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Located:
    """Where a trigger is recorded.

    Attributes
    ----------
    file : str
        The file's name within the recordings folder.
    start_ns, end_ns : int
        Log times of the trigger's first and last message, ns since the epoch.
    topics : list of str
        The topics that hold its messages (frames only where the retention kept them).
    finished : bool
        The file is complete and indexed (else still being written).
    """

    file: str
    start_ns: int
    end_ns: int
    topics: list[str] = field(default_factory=list)
    finished: bool = True


def locate(directory: Path, result_id: str, triggered_ns: int) -> Located | None:
    """The recording of the result ``result_id`` logged at ``triggered_ns``, or None."""
    if not directory.is_dir():
        return None
    files = sorted(directory.glob("*.mcap"), key=lambda p: p.stat().st_mtime, reverse=True)
    for path in files:
        try:
            found = (_indexed if is_finished(path) else _streamed)(path, result_id, triggered_ns)
        except Exception as exc:  # a damaged or vanished file holds nothing we can point to
            log.info("%s: not searched (%s)", path.name, exc)
            continue
        if found is not None:
            return found
    return None


def _indexed(path: Path, result_id: str, t: int) -> Located | None:
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        stats = summary.statistics if summary is not None else None
        if stats is not None and not stats.message_start_time <= t <= stats.message_end_time:
            return None
        topics: set[str] = set()
        hit = False
        for _, channel, message in reader.iter_messages(starting_at=t, ending_at=t):
            if message.log_time != t:
                continue
            topics.add(channel.topic)
            if channel.topic == "/result" and json.loads(message.data).get("id") == result_id:
                hit = True
    return Located(path.name, t, t, sorted(topics), True) if hit else None


def _streamed(path: Path, result_id: str, t: int) -> Located | None:
    """Search the file being written: only the chunks whose time range holds ``t`` are
    unpacked. A message on a channel that was declared in a skipped chunk sends the
    search through every record instead."""
    channels: dict[int, str] = {}
    topics: set[str] = set()
    hit = False
    with path.open("rb") as fh:
        reader = StreamReader(fh, skip_magic=False, emit_chunks=True)
        try:
            for rec in reader.records:
                if isinstance(rec, Chunk):
                    if not rec.message_start_time <= t <= rec.message_end_time:
                        continue
                    inner = breakup_chunk(rec)
                else:
                    inner = [rec]
                for r in inner:
                    if isinstance(r, Channel):
                        channels[r.id] = r.topic
                    elif isinstance(r, Message) and r.log_time == t:
                        if r.channel_id not in channels:
                            return _streamed_all(path, result_id, t)
                        topic = channels[r.channel_id]
                        topics.add(topic)
                        if topic == "/result" and json.loads(r.data).get("id") == result_id:
                            hit = True
        except Exception as exc:  # a torn record at the end of the file being written
            log.info("%s: stopped at a damaged record (%s)", path.name, exc)
    return Located(path.name, t, t, sorted(topics), False) if hit else None


def _streamed_all(path: Path, result_id: str, t: int) -> Located | None:
    channels: dict[int, str] = {}
    topics: set[str] = set()
    hit = False
    for rec in iter_records(path):
        if isinstance(rec, Channel):
            channels[rec.id] = rec.topic
        elif isinstance(rec, Message) and rec.log_time == t:
            topic = channels.get(rec.channel_id, "")
            topics.add(topic)
            if topic == "/result" and json.loads(rec.data).get("id") == result_id:
                hit = True
    return Located(path.name, t, t, sorted(topics), False) if hit else None
