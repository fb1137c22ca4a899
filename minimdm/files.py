"""Files written whole or not at all, and one training run per output folder.

The design's rule is that nothing is lost: a failed or interrupted write never leaves a torn file
where a good one was, and two runs never write into one folder. This module is the one place
that does both.

* :func:`atomic_write` writes bytes or text; :func:`atomic_output` lends a temporary path to
  writers that want a file name (numpy, PIL, imageio, ONNX). Either way the data go to a
  temporary file ``.NAME.tmpPID`` beside the target, are synced to disk and renamed over the
  target with ``os.replace``. On any failure the temporary file is removed and the target is
  left as it was; a failed write (a full disk, a read-only folder) raises :class:`WriteError`,
  an ``OSError`` whose message names the file. Temporary files of writers that were killed
  between writing and renaming are removed by the next write of the same file.
* :class:`RunLock` holds :data:`LOCK_NAME` in a training run's output folder for the length of
  the run. A second run that asks for the same folder is refused with :class:`LockedError`,
  naming the first (pid, host, start time, command). The lock is an ``flock`` on the file, which
  the kernel drops when its process dies, even by ``kill -9``; the file itself stays behind, and
  the next run takes it over with a warning that names the dead run.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import sys
import time
import warnings
from collections.abc import Iterator
from glob import escape as glob_escape
from pathlib import Path
from typing import IO, Any

from minimdm.validate import InputError

try:  # POSIX; without it (Windows) the lock falls back on the recorded pid alone
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

__all__ = ["WriteError", "LockedError", "LOCK_NAME", "atomic_write", "atomic_output", "RunLock"]

LOCK_NAME = "run.lock"
"""The lock file a training run holds in its output folder."""


class WriteError(OSError):
    """A file could not be written (no space left, no permission, a read-only disk); the message
    names the file. Nothing was left behind: the target is as it was, the temporary file gone."""

    def __init__(self, path: Path, cause: OSError) -> None:
        super().__init__(f"cannot write {path}: {cause.strerror or cause}")
        self.errno = cause.errno
        self.path = path


class LockedError(InputError):
    """Another live run holds the output folder's lock; the message names it."""


# --------------------------------------------------------------------------------------------
# Atomic writes


def _pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (one we may not signal counts)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: it exists, under another user
        return True
    return True


def _temp_path(path: Path, suffix: str = "") -> Path:
    return path.with_name(f".{path.name}.tmp{os.getpid()}{suffix}")


def _remove_stale_temps(path: Path) -> list[Path]:
    """Delete ``.NAME.tmp<PID>[SUFFIX]`` files beside ``path`` left by writers that died between
    writing and renaming; returns them. A live writer's file is kept."""
    removed = []
    prefix = f".{path.name}.tmp"
    for tmp in path.parent.glob(f"{glob_escape(prefix)}*"):
        rest = tmp.name[len(prefix) :]
        pid = rest[: len(rest) - len(rest.lstrip("0123456789"))]
        if not pid or rest[len(pid) :] not in ("", path.suffix):
            continue
        if int(pid) != os.getpid() and not _pid_alive(int(pid)):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def _write(f: IO[bytes], data: bytes) -> None:
    """Write ``data`` to an open file (a seam for tests that simulate a full disk)."""
    f.write(data)


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: not every system can open a folder)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _prepare(path: str | os.PathLike) -> Path:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise WriteError(path, e) from e
    _remove_stale_temps(path)
    return path


def _commit(tmp: Path, path: Path) -> None:
    """Sync ``tmp`` and rename it over ``path``."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    _fsync_folder(path.parent)


def atomic_write(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` (bytes, or text as UTF-8) to ``path`` whole or not at all; returns ``path``.

    Raises:
        WriteError: the file could not be written; ``path`` is as it was and no temporary file
            is left.
    """
    blob = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        _write(f, blob)
    return Path(path)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` with the same suffix, renamed over ``path`` when the
    block ends without an error (removed when it raises)::

        with atomic_output("walk.npz") as tmp:
            np.savez_compressed(tmp, positions=pos)

    Raises:
        WriteError: the writer or the rename failed with an ``OSError`` (a full disk...).
    """
    path = _prepare(path)
    tmp = _temp_path(path, path.suffix)
    try:
        yield tmp
        if not tmp.is_file():
            raise FileNotFoundError(errno.ENOENT, f"the writer wrote nothing to {tmp.name}")
        _commit(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise WriteError(path, e) from e
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------------------------
# One run per output folder


def _describe_run(record: dict[str, Any]) -> str:
    """``pid 123 on host, started 2026-01-01T10:00:00, command: minimdm train ...``."""
    if not record:
        return "a run that is still writing the lock"
    return (
        f"pid {record.get('pid', '?')} on {record.get('host', '?')}, started "
        f"{record.get('started', '?')}, command: {record.get('command') or '?'}"
    )


def _read_record(fd: int) -> dict[str, Any]:
    os.lseek(fd, 0, os.SEEK_SET)
    data = b""
    while chunk := os.read(fd, 1 << 16):
        data += chunk
    try:
        record = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return {}
    return record if isinstance(record, dict) else {}


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    own = os.fstat(fd)
    return (own.st_dev, own.st_ino) == (st.st_dev, st.st_ino)


class RunLock:
    """``with RunLock(out_dir, command):`` holds ``out_dir/run.lock`` for the run (module
    docstring).

    The lock is re-entrant within a process (a trainer that calls another trainer on the same
    folder holds it once). Under ``torchrun`` only rank 0 takes it: rank 0 alone writes.

    Raises:
        LockedError: another live run holds the folder; the message names its pid, host, start
            time and command. A lock left by a run that died is taken over with a warning.
    """

    _held: dict[Path, int] = {}  # folder -> depth, this process's locks

    def __init__(self, folder: str | os.PathLike, command: str | None = None) -> None:
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.command = command or " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]).strip()
        self._fd: int | None = None
        self._key: Path | None = None
        self._made = False  # the lock made the folder: an empty one goes again at the end

    def __enter__(self) -> RunLock:
        if int(os.environ.get("RANK", "0") or 0) != 0:
            return self
        key = self.folder.resolve()
        if key in RunLock._held:
            RunLock._held[key] += 1
            self._key = key
            return self
        made = not self.folder.exists()
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise WriteError(self.path, e) from e
        try:
            self._fd = self._acquire()
        except BaseException:
            if made:
                with contextlib.suppress(OSError):
                    self.folder.rmdir()
            raise
        self._key, self._made = key, made
        RunLock._held[key] = 1
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._key is None:
            return
        RunLock._held[self._key] -= 1
        if RunLock._held[self._key] == 0:
            del RunLock._held[self._key]
            if self._fd is not None:
                if _same_file(self._fd, self.path):
                    self.path.unlink(missing_ok=True)
                os.close(self._fd)  # drops the flock
                self._fd = None
                if self._made:  # a run that failed before writing anything leaves no folder
                    with contextlib.suppress(OSError):
                        self.folder.rmdir()
        self._key = None

    def _refuse(self, record: dict[str, Any], why: str = "") -> LockedError:
        return LockedError(
            f"{self.folder} is in use by another run ({_describe_run(record)}){why}; wait for "
            "it to finish or write elsewhere"
        )

    def _acquire(self) -> int:
        host = socket.gethostname()
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as e:
                raise WriteError(self.path, e) from e
            try:
                if fcntl is not None:
                    try:
                        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    except BlockingIOError:
                        raise self._refuse(_read_record(fd)) from None
                if not _same_file(fd, self.path):  # its holder removed it meanwhile: again
                    os.close(fd)
                    continue
                old = _read_record(fd)
                pid = old.get("pid")
                if old and old.get("host") != host:
                    why = "; this machine cannot tell whether it still runs: delete"
                    raise self._refuse(old, f"{why} {self.path} if it does not")
                if isinstance(pid, int) and pid != os.getpid() and _pid_alive(pid):
                    raise self._refuse(old)  # only where the file system ignores flock
                if old:
                    warnings.warn(
                        f"{self.path}: took over the lock of a run that no longer runs "
                        f"({_describe_run(old)})",
                        stacklevel=3,
                    )
                record = {
                    "pid": os.getpid(),
                    "host": host,
                    "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                    "command": self.command,
                }
                try:
                    os.ftruncate(fd, 0)
                    os.lseek(fd, 0, os.SEEK_SET)
                    os.write(fd, (json.dumps(record) + "\n").encode("utf-8"))
                    os.fsync(fd)
                except OSError as e:
                    raise WriteError(self.path, e) from e
                return fd
            except BaseException:
                os.close(fd)
                raise
