"""Files written for the user, atomically: a hidden temporary file beside the target, then ``os.replace``.

The temporary file is created as ``open()`` would create the target itself, with mode 0o666 less the
user's umask (``tempfile.mkstemp`` makes it 0600, and ``os.replace`` would hand that mode on to the
user's file: a CSV or HDF5 file other users and tools could not read).
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

TMP_PREFIX = ".tmp-"


def temporary_beside(target: str | os.PathLike, suffix: str) -> Path:
    """A new, empty, hidden file in ``target``'s directory with the user's umask applied (the kernel
    applies it to mode 0o666); OSError when it cannot be created (no directory, no permission)."""
    tmp = Path(target).parent / f"{TMP_PREFIX}{os.getpid()}-{secrets.token_hex(6)}{suffix}"
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    return tmp
