"""The worker's journal: every FrameSet it accepted and has not answered yet, on disk.

A FrameSet is written here, durably (the file and its directory synced),
when it is received, and deleted once its result has gone to every sink. A
worker that is killed therefore finds, at its next start, exactly the
triggers it had accepted and not finished: it measures them again (or,
when one is already in the store, drops the entry) before it takes new
frames. A file that was being written when the process died never got its
final name and is discarded: that trigger was not accepted, and the seq
gap it leaves is answered as ``missed``.

One file per FrameSet, ``<received_ns>-<n>.fs``, holding the bytes as they
came off the bus; the name orders the entries as they were received.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

SUFFIX = ".fs"


@dataclass(frozen=True)
class Entry:
    """One journaled FrameSet: its key (file stem), bytes and receive time."""

    key: str
    payload: bytes
    received_ns: int


class Journal:
    """FrameSets accepted and not yet answered, one synced file each.

    Parameters
    ----------
    directory : str or Path
        Created if missing. One worker per directory.
    max_entry_bytes : int
        A FrameSet larger than this is not journaled (it is still measured);
        the bus's own message limit is far below the default.
    """

    def __init__(self, directory: str | Path, *, max_entry_bytes: int = 1 << 30) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.max_entry_bytes = max_entry_bytes
        self._lock = threading.Lock()
        self._n = 0
        for torn in self.directory.glob("*.tmp"):
            log.warning("journal: discarding %s, written when the worker stopped", torn.name)
            torn.unlink(missing_ok=True)

    def add(self, payload: bytes, received_ns: int) -> str | None:
        """Write one FrameSet durably; returns its key, or None when it was not kept.

        Not kept: larger than ``max_entry_bytes``, or the disk refused it (both
        logged). The FrameSet is measured either way; only a kill before its
        result would then lose it.
        """
        if len(payload) > self.max_entry_bytes:
            log.warning("journal: a %d-byte FrameSet is not journaled", len(payload))
            return None
        with self._lock:
            self._n += 1
            key = f"{received_ns:020d}-{self._n:06d}"
        tmp = self.directory / f"{key}.tmp"
        try:
            with tmp.open("wb") as fh:
                fh.write(payload)
                fh.flush()
                os.fsync(fh.fileno())
            tmp.replace(self.directory / f"{key}{SUFFIX}")
            _sync_dir(self.directory)
        except OSError as exc:
            log.error("journal: FrameSet not journaled: %s", exc)
            tmp.unlink(missing_ok=True)
            return None
        return key

    def remove(self, key: str | None) -> None:
        """Forget an answered FrameSet (None: it was never journaled)."""
        if key is None:
            return
        try:
            (self.directory / f"{key}{SUFFIX}").unlink(missing_ok=True)
        except OSError as exc:
            log.error("journal: %s not removed: %s", key, exc)

    def pending(self) -> list[Entry]:
        """Every journaled FrameSet, oldest first."""
        out = []
        for path in sorted(self.directory.glob(f"*{SUFFIX}")):
            key = path.stem
            try:
                received_ns = int(key.split("-", 1)[0])
                payload = path.read_bytes()
            except (ValueError, OSError) as exc:
                log.error("journal: %s unreadable, dropped: %s", path.name, exc)
                path.unlink(missing_ok=True)
                continue
            out.append(Entry(key, payload, received_ns))
        return out

    def __len__(self) -> int:
        return sum(1 for _ in self.directory.glob(f"*{SUFFIX}"))


def _sync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (the directory entry itself synced)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
