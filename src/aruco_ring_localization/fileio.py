"""Safe file writing: a file is replaced whole or not at all.

:func:`atomic_write_text` writes to a temporary file in the same directory, flushes and fsyncs it,
keeps the previous version as ``<name>.bak`` (and, with ``backups=N``, the ones before as
``<name>.bak.2`` ... ``<name>.bak.N``, newest first) and renames the new one into place. A process
killed at any instant leaves either the old file or the new one (and the backups), never half a
file.
A new file gets the mode an ``open()`` would give it (0666 less the umask: 0644 by default); a
replaced file keeps its own mode.
"""
from __future__ import annotations

import logging
import os
import secrets
import stat
from typing import List

from .errors import ConfigError

logger = logging.getLogger(__name__)


def backup_paths(path: str, backups: int) -> List[str]:
    """The backups of ``path``, newest first: ``path.bak``, ``path.bak.2``, ... (``backups`` of them)."""
    return [f"{path}.bak" if k == 1 else f"{path}.bak.{k}" for k in range(1, int(backups) + 1)]


def atomic_write_text(path: str, text: str, keep_backup: bool = True, backups: int = 1) -> None:
    """Write ``text`` to ``path`` atomically.

    With ``keep_backup``, the previous file becomes ``path + '.bak'`` and the ``backups - 1``
    before it move down to ``.bak.2`` ... ``.bak.<backups>`` (the oldest goes); ``backups`` 0 or
    ``keep_backup`` False keeps none.
    """
    if not keep_backup:
        backups = 0
    path = os.path.abspath(str(path))
    directory = os.path.dirname(path)
    try:
        os.makedirs(directory, exist_ok=True)
        _remove_stale_temporaries(path)
        fd, tmp = _create_temporary(path)
    except OSError as exc:
        raise ConfigError(f"cannot create a file in {directory} ({exc})", path=path) from None
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        if backups > 0 and os.path.exists(path):
            baks = backup_paths(path, backups)
            # Oldest first, each rename atomic: a kill in between loses at most the oldest backup.
            for older, newer in zip(baks[::-1], baks[-2::-1]):
                if os.path.lexists(newer):
                    os.replace(newer, older)
            # A hard link keeps the old file reachable as .bak while the rename below replaces it,
            # so there is no instant at which neither the old nor the new map exists.
            bak = baks[0]
            try:
                if os.path.lexists(bak):
                    os.unlink(bak)
                os.link(path, bak)
            except OSError:
                import shutil

                shutil.copy2(path, bak)
        os.replace(tmp, path)
        _fsync_dir(directory)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise ConfigError(f"cannot write file ({exc})", path=path) from None
        raise


def _create_temporary(path: str):
    """(fd, name) of a new temporary beside ``path``, with the mode the final file should have.

    ``tempfile.mkstemp`` creates 0600 files, which the rename would hand on to every map and
    result. Here the kernel applies the umask to 0666 itself (no process-wide ``os.umask`` call,
    which would race with other threads); an existing file's mode is kept.
    """
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        mode = None
    while True:
        tmp = os.path.join(os.path.dirname(path), f".{os.path.basename(path)}.{secrets.token_hex(4)}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        if mode is not None:
            os.fchmod(fd, mode)
        return fd, tmp


def _remove_stale_temporaries(path: str, older_than: float = 60.0) -> None:
    """Delete temporaries of ``path`` left by a writer that was killed mid-save.

    Only files older than ``older_than`` seconds go, so a save in progress elsewhere is left alone.
    """
    import glob
    import time

    pattern = os.path.join(os.path.dirname(path), "." + glob.escape(os.path.basename(path)) + ".*.tmp")
    limit = time.time() - older_than
    for tmp in glob.glob(pattern):
        try:
            if os.path.getmtime(tmp) < limit:
                os.unlink(tmp)
                logger.info("removed %s, left by an interrupted save", tmp)
        except OSError:
            pass


def _fsync_dir(directory: str) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
