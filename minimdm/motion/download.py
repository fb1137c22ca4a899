"""Fetching and unpacking corpus archives: resumable, checked, never half-unpacked.

Two steps, used by :func:`minimdm.motion.corpora.download_corpus` (``minimdm data download``):

1. :func:`fetch` streams a URL into ``DEST.part`` with ``urllib`` and a progress bar. When a
   ``.part`` file is already there (an earlier run was interrupted), it asks the server for the
   rest with an HTTP ``Range`` request; a server that ignores it (status 200, not 206) sends the
   whole file again, and the download restarts cleanly from byte 0. Only a whole file is renamed
   to ``DEST``.
2. :func:`unpack` extracts a zip or tar archive into a temporary folder beside the target, writes
   the ``.complete`` marker and renames the folder into place: an interrupted extraction leaves
   no folder that looks complete. Extraction is safe: tar members go through
   ``filter="data"`` and zip members whose path would leave the folder are refused.

**Checks.** When the caller knows the archive's size and SHA-256, :func:`fetch` compares them
with what arrived and refuses a mismatch, deleting the bad file. When it does not know them (the
registry records ``None``: we never guess a hash), :func:`fetch` only *computes* the SHA-256 and
returns it; :func:`~minimdm.motion.corpora.download_corpus` prints it and, once the archive has
unpacked, records it in the data folder, and checks later downloads against that record (trust
on first use). A download that fails a check (size, hash, not an archive, no such folder in it,
an unsafe member) is deleted and records nothing. Such a record
proves only that later downloads equal the first one, not that the first one was genuine.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import shutil
import tarfile
import tempfile
import urllib.error
import urllib.parse
import urllib.request
import zipfile
from pathlib import Path, PurePosixPath

from tqdm.auto import tqdm

from minimdm.files import atomic_write

__all__ = ["DONE", "DownloadError", "fetch", "sha256_of", "unpack"]

DONE = ".complete"
"""Written last into an unpacked folder: a folder without it is a partial extraction."""

CHUNK = 1 << 16
"""Bytes read and written at a time."""


class DownloadError(RuntimeError):
    """A download that could not be made or checked (no network, wrong size, wrong hash)."""


def sha256_of(path: str | Path) -> str:
    """The SHA-256 hex digest of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def _check(path: Path, got_size: int, got_sha: str, size: int | None, sha256: str | None) -> None:
    """Refuse (and delete) a file whose size or hash differs from the expected ones."""
    if size is not None and got_size != size:
        path.unlink(missing_ok=True)
        raise DownloadError(f"{path.name}: expected {size} bytes, got {got_size}; deleted it")
    if sha256 is not None and got_sha != sha256.lower():
        path.unlink(missing_ok=True)
        raise DownloadError(
            f"{path.name}: SHA-256 {got_sha} is not the expected {sha256}; deleted it"
        )


def _open(url: str, start: int, timeout: float, dest: Path):
    """``urlopen`` asking for bytes ``start..`` (if > 0), with one-line errors.

    Returns None when the server refuses the range (HTTP 416).
    """
    req = urllib.request.Request(url, headers={"User-Agent": "minimdm"})
    if start:
        req.add_header("Range", f"bytes={start}-")
    try:
        return urllib.request.urlopen(req, timeout=timeout)
    except urllib.error.HTTPError as e:  # the server answered: not a network problem
        if e.code == 416 and start:  # "range not satisfiable": the .part is no prefix
            return None
        raise DownloadError(f"{url}: HTTP {e.code} {e.reason}") from None
    except (urllib.error.URLError, OSError) as e:
        host = urllib.parse.urlsplit(url).hostname or url
        reason = getattr(e, "reason", e)
        raise DownloadError(
            f"cannot reach {host} ({reason}); no network? Copy the archive to {dest} and run again"
        ) from None


def fetch(
    url: str,
    dest: str | Path,
    *,
    size: int | None = None,
    sha256: str | None = None,
    progress: bool = True,
    timeout: float = 30.0,
) -> str:
    """Download ``url`` to ``dest`` (resuming ``dest.part``), check it, return its SHA-256.

    Args:
        url: an ``http(s)://`` or ``file://`` address.
        dest: where the whole file goes. If it already exists it is only checked.
        size: expected bytes, or None (unknown: not checked).
        sha256: expected hex digest, or None (unknown: computed and returned, not checked).
        progress: show a tqdm progress bar.
        timeout: seconds to wait for the server.

    Raises:
        DownloadError: no connection, an HTTP error, or a size/hash mismatch (the bad file is
            deleted). An interrupted transfer keeps ``dest.part`` for the next run to resume.
    """
    dest = Path(dest)
    if dest.exists():  # downloaded earlier, or copied there by hand
        digest = sha256_of(dest)
        _check(dest, dest.stat().st_size, digest, size, sha256)
        return digest
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    have = part.stat().st_size if part.exists() else 0
    resp = _open(url, have, timeout, dest)
    if resp is None:
        part.unlink()
        have, resp = 0, _open(url, 0, timeout, dest)
    with resp:
        status = getattr(resp, "status", None)  # None for file://, which ignores Range
        if have and status != 206:  # the server sent the whole file: restart from byte 0
            have = 0
        elif have and not resp.headers.get("Content-Range", "").startswith(f"bytes {have}-"):
            part.unlink()
            raise DownloadError(f"{url}: the server sent another range than bytes {have}-")
        length = resp.headers.get("Content-Length")
        total = have + int(length) if length and length.isdigit() else size
        h = hashlib.sha256()
        if have:  # hash what we already have, then append
            with open(part, "rb") as f:
                for block in iter(lambda: f.read(CHUNK), b""):
                    h.update(block)
        bar = tqdm(total=total, initial=have, unit="B", unit_scale=True, disable=not progress)
        got = have
        try:
            with open(part, "ab" if have else "wb") as f:
                for block in iter(lambda: resp.read(CHUNK), b""):
                    f.write(block)
                    h.update(block)
                    got += len(block)
                    bar.update(len(block))
                f.flush()
                os.fsync(f.fileno())  # on disk before it is renamed whole
            if length and length.isdigit() and got != total:  # closed early, without an error
                raise ConnectionError(f"the server promised {total} bytes")
        except (OSError, http.client.HTTPException) as e:  # lost mid-way: keep .part to resume
            raise DownloadError(
                f"download of {url} interrupted after {got} bytes ({e}); run again to resume"
            ) from None
        finally:
            bar.close()
    digest = h.hexdigest()
    _check(part, got, digest, size, sha256)
    os.replace(part, dest)
    return digest


def _safe_member(name: str) -> bool:
    """True when a zip member's path stays inside the folder it is extracted to."""
    p = PurePosixPath(name.replace("\\", "/"))
    return not p.is_absolute() and ".." not in p.parts and ":" not in name


def _extract_zip(archive: Path, out: Path) -> None:
    with zipfile.ZipFile(archive) as zf:
        bad = [m for m in zf.namelist() if not _safe_member(m)]
        if bad:
            raise DownloadError(f"{archive.name}: refusing members outside the folder: {bad[:3]}")
        zf.extractall(out)


def _extract_tar(archive: Path, out: Path) -> None:
    with tarfile.open(archive) as tar:
        try:
            tar.extractall(out, filter="data")  # refuses absolute paths, '..', links out
        except tarfile.FilterError as e:
            raise DownloadError(f"{archive.name}: refusing an unsafe member: {e}") from None


def unpack(archive: str | Path, target: str | Path, member: str = "", stamp: str = "") -> Path:
    """Extract ``archive`` (zip or tar.*) so that its folder ``member`` becomes ``target``.

    Args:
        archive: a ``.zip`` or ``.tar[.gz|.bz2|.xz]`` file.
        target: the folder to create; a partial one (no ``.complete``) is replaced.
        member: the folder inside the archive that becomes ``target`` ('' = the archive's root),
            e.g. ``"repo-main/dataset/corpus"`` for a GitHub archive.
        stamp: text of the ``.complete`` marker (say where the archive came from).

    Returns:
        ``target``, holding ``.complete``.
    """
    archive, target = Path(archive), Path(target)
    if member and not _safe_member(member):
        raise ValueError(f"member must be a relative path inside the archive, got {member!r}")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}-", dir=target.parent))
    try:
        if zipfile.is_zipfile(archive):
            _extract_zip(archive, tmp / "x")
        elif tarfile.is_tarfile(archive):
            _extract_tar(archive, tmp / "x")
        else:
            raise DownloadError(f"{archive} is neither a zip nor a tar archive")
        src = tmp / "x" / member if member else tmp / "x"
        if not src.is_dir():
            raise DownloadError(f"{archive.name} holds no folder {member!r}")
        atomic_write(src / DONE, stamp + "\n")
        if (target / DONE).exists():  # another process unpacked it meanwhile: keep theirs,
            return target  # it may be reading it (two benchmark processes on a new machine)
        if target.exists():  # a partial folder from an earlier, interrupted attempt
            shutil.rmtree(target)
        try:
            os.replace(src, target)  # atomic: the folder appears whole, marker included
        except OSError:
            if not (target / DONE).exists():  # not a race lost to another process
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target
