"""The files of a live SQLite database, watched from the serving process without ever closing a
descriptor of them.

POSIX advisory locks belong to a process and a file, not to a descriptor: closing ANY descriptor of
the database file drops every lock this process holds on it, SQLite's own included (the documented
pitfall, https://www.sqlite.org/howtocorrupt.html §2.2).  A plain ``open(db).read(); close()`` after
each commit did exactly that; another process that then closed its own connection believed it was
the last user, checkpointed and deleted the live write-ahead log, and the commits this process made
afterwards went into a deleted file: acknowledged chunks gone at the next restart.

So the serving process opens each watched file ONCE, reads it with ``os.pread`` and ``os.fstat``, and
closes the descriptors only when the last store of this process watching that file closes
(:func:`watch` / :meth:`FileWatch.release`, reference-counted by inode).  Identity checks use
``os.stat`` on the path, which opens nothing.

A :class:`Finding` says what a look found and whether it is *certain* (the file removed or replaced,
the write-ahead log vanished or replaced: nothing else can explain it) or only a *doubt* that a
checkpoint running in another thread or process can cause for a moment (the header's page count
above the file's size, written before the file grows; a write-ahead log header half rewritten), to
be confirmed before the store is declared damaged.
"""

from __future__ import annotations

import os
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

SQLITE_MAGIC = b"SQLite format 3\x00"
WAL_MAGIC = (0x377F0682, 0x377F0683)  # little- / big-endian checksums


@dataclass(frozen=True)
class Finding:
    """What is wrong with the files (``text`` completes "the session database ..."), whether it is
    certain or a doubt to confirm, and whether SQLite's own check can settle the doubt (a short file:
    quick_check reads every page of a consistent snapshot) or only time can (a log header: SQLite
    rewrites it in one write when it restarts the log, so a bad one that stays bad was overwritten)."""

    text: str
    certain: bool
    sqlite_decides: bool = False


class _Kept:
    """One read-only descriptor of a file, shared by the stores of this process that watch it."""

    def __init__(self, path: Path):
        self.fd = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        st = os.fstat(self.fd)
        self.identity = (st.st_dev, st.st_ino)
        self.users = 0


_KEPT: dict[tuple[int, int], _Kept] = {}
_LOCK = threading.Lock()


def _keep(path: Path) -> _Kept:
    """The kept descriptor of the file at ``path`` now (opened once per inode and process)."""
    st = os.stat(path)
    with _LOCK:
        kept = _KEPT.get((st.st_dev, st.st_ino))
        if kept is None:
            kept = _Kept(path)
            _KEPT[kept.identity] = kept
        kept.users += 1
        return kept


def _release(kept: _Kept) -> None:
    """Close the descriptor when no store of this process watches its file any more (only then: the
    close drops this process's locks on the file)."""
    with _LOCK:
        kept.users -= 1
        if kept.users <= 0 and _KEPT.get(kept.identity) is kept:
            del _KEPT[kept.identity]
            os.close(kept.fd)


class FileWatch:
    """The database file and its write-ahead log as they were when the store opened them."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.wal_path = Path(f"{self.path}-wal")
        self._db = _keep(self.path)
        try:
            self._wal = _keep(self.wal_path)  # exists: the store's connections are open in WAL mode
        except FileNotFoundError:
            self._wal = None
        except BaseException:
            _release(self._db)
            raise

    def release(self) -> None:
        for kept in (self._db, self._wal):
            if kept is not None:
                _release(kept)
        self._db = self._wal = None  # type: ignore[assignment]

    def look(self) -> Finding | None:
        """None when both files are the ones opened and their headers agree with their sizes."""
        return self._identity() or self._header() or self._wal_header()

    def _identity(self) -> Finding | None:
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return Finding("was removed", True)
        except OSError as exc:
            return Finding(f"cannot be examined ({exc.strerror})", False)
        if (st.st_dev, st.st_ino) != self._db.identity:
            return Finding("was replaced by another file", True)
        if self._wal is None:
            return None
        try:
            st = os.stat(self.wal_path)
        except FileNotFoundError:
            return Finding("lost its write-ahead log (deleted under the server: the commits since the last "
                           "checkpoint would be lost at a restart)", True)
        except OSError as exc:
            return Finding(f"has a write-ahead log that cannot be examined ({exc.strerror})", False)
        if (st.st_dev, st.st_ino) != self._wal.identity:
            return Finding("had its write-ahead log replaced by another file", True)
        return None

    def _header(self) -> Finding | None:
        header = os.pread(self._db.fd, 100, 0)
        if len(header) < 100 or not header.startswith(SQLITE_MAGIC):
            return Finding("was truncated or overwritten (no SQLite header)", False, True)
        page_size = struct.unpack(">H", header[16:18])[0]
        page_size = 65536 if page_size == 1 else page_size
        pages = struct.unpack(">I", header[28:32])[0]
        size = os.fstat(self._db.fd).st_size
        if size < pages * page_size:  # also for a moment while a checkpoint grows the file
            return Finding(f"was truncated ({size} bytes, its header says {pages * page_size})", False, True)
        return None

    def _wal_header(self) -> Finding | None:
        if self._wal is None:
            return None
        return wal_header_problem(os.pread(self._wal.fd, 32, 0))


def wal_header_problem(header: bytes) -> Finding | None:
    """The write-ahead log's 32-byte header: magic, and its checksum (SQLite's wal.c algorithm).  A doubt
    only: SQLite rewrites the header when it restarts the log after a checkpoint."""
    if len(header) == 0:
        return None  # reset after a checkpoint
    if len(header) < 32:
        return Finding("has a truncated write-ahead log header", False)
    magic = struct.unpack(">I", header[:4])[0]
    if magic not in WAL_MAGIC:
        return Finding("has an overwritten write-ahead log (bad magic number)", False)
    order = ">" if magic & 1 else "<"
    words = struct.unpack(f"{order}6I", header[:24])
    s0 = s1 = 0
    for i in range(0, 6, 2):
        s0 = (s0 + words[i] + s1) & 0xFFFFFFFF
        s1 = (s1 + words[i + 1] + s0) & 0xFFFFFFFF
    if (s0, s1) != struct.unpack(">2I", header[24:32]):
        return Finding("has an overwritten write-ahead log (header checksum)", False)
    return None
