"""How the toolkit writes and opens its own files: atomically, and uninflated.

Both file formats (:mod:`models.params`, torch's zip; :mod:`models.portable`, numpy's
npz) are zip archives whose members are stored, not compressed, and are written the same
way: built in memory, written beside the target under a fresh temporary name, flushed to
disk, then renamed over the target, so that a failed save (a full disk, a kill) leaves
the file that was there.
"""

from __future__ import annotations

import errno
import os
import secrets
import zipfile
from pathlib import Path


def target_file(path: str | Path) -> Path:
    """``path`` as the file a save writes, refused if it is a folder."""
    path = Path(path)
    if path.is_dir():  # the rename would fail last, naming the temporary file
        raise ValueError(f"{str(path)!r} is a folder; expected the path of the file to save")
    return path


def write_atomically(path: Path, content: bytes | memoryview) -> Path:
    """Write ``content`` to ``path`` through a temporary file renamed over it.

    Raises
    ------
    OSError
        The system's, with the temporary file removed; a full disk (``ENOSPC``) names
        ``path`` and says that the previous file is kept.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        # O_EXCL: a fresh file of our own; mode 0o666 minus the umask, as open() gives
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(content)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.errno == errno.ENOSPC:
            raise OSError(
                exc.errno,
                f"No space left on device: cannot save {path} ({len(content)} bytes); the "
                "file that was there is kept. Free some space or save elsewhere",
                str(path),
            ) from exc
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def stored_members(path: Path, what: str) -> list[zipfile.ZipInfo]:
    """The members of the zip archive ``path``, refused unread if any is compressed or encrypted.

    A small compressed file can inflate to gigabytes; the toolkit's saves compress
    nothing, so a stored member's size is its size on disk. ``what`` names the format
    in the error.

    Raises
    ------
    FileNotFoundError
        If there is no file.
    ValueError
        If it is not a zip archive, or a member is compressed or encrypted.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
    except FileNotFoundError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as exc:
        raise ValueError(f"{path} is not a readable {what} ({type(exc).__name__}: {exc})") from exc
    for m in members:
        if m.flag_bits & 0x1:  # the toolkit's saves encrypt nothing either
            raise ValueError(
                f"{path} is not a {what} as the toolkit writes it: its member "
                f"{m.filename!r} is marked encrypted (a changed byte?); refused unread"
            )
        if m.compress_type != zipfile.ZIP_STORED:
            raise ValueError(
                f"{path} is not a {what} as the toolkit writes it: its member "
                f"{m.filename!r} is compressed ({m.file_size} bytes inflated); refused "
                "unread"
            )
    return members
