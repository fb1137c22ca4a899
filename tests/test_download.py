"""`minimdm data download` against a local mirror: file:// archives and a loopback HTTP server.

No test touches the network: archives are built in tmp_path and served from 127.0.0.1.
"""

import hashlib
import http.server
import io
import tarfile
import threading
import zipfile

import pytest

from minimdm.cli import main
from minimdm.motion import corpora, download
from minimdm.motion.corpora import Corpus, download_corpus
from minimdm.motion.download import DownloadError

TAKES = {
    "a.bvh": b"HIERARCHY\nROOT Hips\n" + bytes(range(256)) * 40,
    "b.bvh": b"HIERARCHY\nROOT Pelvis\n" + bytes(range(255, -1, -1)) * 40,
}
MEMBER = "repo-main/dataset/tiny"


def _zip_bytes(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _targz_bytes(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


ZIP = _zip_bytes({f"{MEMBER}/{k}": v for k, v in TAKES.items()} | {"repo-main/README": b"hi"})


@pytest.fixture
def home(tmp_path, monkeypatch):
    d = tmp_path / "home"
    monkeypatch.setenv("MINIMDM_DATA", str(d))
    return d


def _register(monkeypatch, url, **changes):
    """A corpus 'tiny' in the registry, fetched from ``url``."""
    fields = dict(
        name="tiny",
        description="two takes",
        licence="CC0",
        attribution="the tests",
        archive="",
        folder="tiny",
        url=url,
        member=MEMBER,
    )
    monkeypatch.setitem(corpora.CORPORA, "tiny", Corpus(**(fields | changes)))


def _assert_whole(folder):
    assert (folder / ".complete").exists()
    assert {p.name: p.read_bytes() for p in folder.glob("*.bvh")} == TAKES
    assert not (folder / "README").exists()  # only the registry's sub-folder is kept


def _nothing_complete(home):
    return not list(home.rglob(".complete")) and not (home / "tiny").exists()


class _Server(http.server.ThreadingHTTPServer):
    """Serves ``self.files`` on 127.0.0.1, honouring Range unless told not to."""

    def __init__(self):
        super().__init__(("127.0.0.1", 0), _Handler)
        self.files: dict[str, bytes] = {}
        self.honour_range = True
        self.cut_after: int | None = None  # promise the whole file, send only this many bytes
        self.ranges: list[str | None] = []

    def url(self, name):
        return f"http://127.0.0.1:{self.server_address[1]}/{name}"


class _Handler(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        srv = self.server
        data = srv.files.get(self.path.lstrip("/"))
        if data is None:
            self.send_error(404)
            return
        rng = self.headers.get("Range")
        srv.ranges.append(rng)
        start = int(rng.removeprefix("bytes=").rstrip("-")) if rng and srv.honour_range else 0
        self.send_response(206 if start else 200)
        if start:
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        self.send_header("Content-Length", str(len(data) - start))
        self.end_headers()
        body = data[start:]
        self.wfile.write(body if srv.cut_after is None else body[: srv.cut_after])

    def log_message(self, *args):
        pass


@pytest.fixture
def server():
    srv = _Server()
    thread = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05})
    thread.daemon = True
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()
    thread.join(timeout=5)


def test_download_unpacks_the_registry_subfolder_and_trusts_the_first_hash(
    home, tmp_path, monkeypatch, capsys
):
    src = tmp_path / "mirror.zip"
    src.write_bytes(ZIP)
    _register(monkeypatch, src.as_uri())
    folder = download_corpus("tiny", progress=False)
    assert folder == home / "tiny"
    _assert_whole(folder)
    digest = hashlib.sha256(ZIP).hexdigest()
    assert digest in capsys.readouterr().out  # printed, since the registry has no hash
    assert (home / "tiny.sha256").read_text().split()[0] == digest
    assert not (home / "tiny.zip").exists() and not (home / "tiny.zip.part").exists()
    assert not [p for p in home.iterdir() if p.name.startswith(".")]  # no temp folder left
    assert corpora.is_present("tiny")
    src.unlink()  # present: nothing is fetched again
    assert download_corpus("tiny", progress=False) == folder
    # the recorded hash is checked later: a changed upstream archive is refused
    src.write_bytes(_zip_bytes({f"{MEMBER}/a.bvh": b"other"}))
    with pytest.raises(DownloadError, match=r"SHA-256.*tiny.sha256.*delete that file"):
        download_corpus("tiny", force=True, progress=False)
    assert _nothing_complete(home) and not (home / "tiny.zip").exists()


@pytest.mark.parametrize(
    "bad, words",
    [
        (b"<html>a web page, not an archive</html>", "neither a zip nor a tar archive"),
        (_zip_bytes({"other-folder/a.bvh": b"x"}), "holds no folder"),
        (_targz_bytes({"tiny/../../evil.bvh": b"x"}), "unsafe member"),
    ],
    ids=["not an archive", "no such folder", "unsafe member"],
)
def test_a_download_that_fails_its_checks_keeps_and_trusts_nothing(
    home, tmp_path, monkeypatch, bad, words
):
    """Issue 27: the file:// of a page was kept and its SHA-256 recorded as trusted, so that
    every later download of the real archive failed the hash check."""
    src = tmp_path / "mirror.archive"
    src.write_bytes(bad)
    _register(monkeypatch, src.as_uri())
    with pytest.raises(DownloadError, match=rf"{words}.*deleted .*recorded no SHA-256"):
        download_corpus("tiny", progress=False)
    assert not home.exists() or list(home.iterdir()) == []  # no archive, no record, no folder
    src.write_bytes(ZIP)  # the real archive then downloads, and only now is its hash trusted
    _assert_whole(download_corpus("tiny", progress=False))
    assert (home / "tiny.sha256").read_text().split()[0] == hashlib.sha256(ZIP).hexdigest()


def test_tar_gz_from_a_url_override(home, tmp_path, monkeypatch):
    src = tmp_path / "mirror.tar.gz"
    src.write_bytes(_targz_bytes({f"{MEMBER}/{k}": v for k, v in TAKES.items()}))
    _register(monkeypatch, "http://127.0.0.1:9/unused.zip")
    _assert_whole(download_corpus("tiny", url=src.as_uri(), progress=False))


def test_a_known_hash_or_size_that_mismatches_is_refused(home, tmp_path, monkeypatch):
    src = tmp_path / "mirror.zip"
    src.write_bytes(ZIP)
    _register(monkeypatch, src.as_uri(), sha256="0" * 64)
    with pytest.raises(DownloadError, match="is not the expected 0000"):
        download_corpus("tiny", progress=False)
    assert _nothing_complete(home) and sorted(p.name for p in home.iterdir()) == []
    _register(monkeypatch, src.as_uri(), size=len(ZIP) + 1)
    with pytest.raises(DownloadError, match=f"expected {len(ZIP) + 1} bytes, got {len(ZIP)}"):
        download_corpus("tiny", progress=False)
    assert _nothing_complete(home) and sorted(p.name for p in home.iterdir()) == []
    # the right size and hash pass, and nothing is recorded (the registry knows them)
    _register(monkeypatch, src.as_uri(), size=len(ZIP), sha256=hashlib.sha256(ZIP).hexdigest())
    _assert_whole(download_corpus("tiny", progress=False))
    assert not (home / "tiny.sha256").exists()


def test_a_partial_download_is_resumed_with_range(home, monkeypatch, server):
    server.files["t.zip"] = ZIP
    _register(monkeypatch, server.url("t.zip"))
    home.mkdir()
    half = len(ZIP) // 2
    (home / "tiny.zip.part").write_bytes(ZIP[:half])
    _assert_whole(download_corpus("tiny", progress=False))
    assert server.ranges == [f"bytes={half}-"]
    assert (home / "tiny.sha256").read_text().split()[0] == hashlib.sha256(ZIP).hexdigest()


def test_a_server_that_ignores_range_restarts_cleanly(home, monkeypatch, server):
    server.files["t.zip"] = ZIP
    server.honour_range = False
    _register(monkeypatch, server.url("t.zip"))
    home.mkdir()
    (home / "tiny.zip.part").write_bytes(b"\xff" * (len(ZIP) // 2))  # no prefix of ZIP
    _assert_whole(download_corpus("tiny", progress=False))
    assert server.ranges == [f"bytes={len(ZIP) // 2}-"]  # asked, was sent the whole file


def test_a_cut_connection_keeps_the_part_and_the_next_run_resumes(home, monkeypatch, server):
    server.files["t.zip"] = ZIP
    server.cut_after = 1000
    _register(monkeypatch, server.url("t.zip"))
    with pytest.raises(DownloadError, match="interrupted after 1000 bytes.*run again to resume"):
        download_corpus("tiny", progress=False)
    assert (home / "tiny.zip.part").read_bytes() == ZIP[:1000]
    assert _nothing_complete(home)
    server.cut_after = None
    _assert_whole(download_corpus("tiny", progress=False))
    assert server.ranges == [None, "bytes=1000-"]


def test_an_interrupted_extraction_leaves_nothing_complete(home, tmp_path, monkeypatch):
    src = tmp_path / "mirror.zip"
    src.write_bytes(ZIP)
    _register(monkeypatch, src.as_uri())
    real = download._extract_zip

    def power_cut(archive, out):
        out.mkdir(parents=True)
        (out / "half.bvh").write_text("HIER")
        raise RuntimeError("power cut")

    monkeypatch.setattr(download, "_extract_zip", power_cut)
    with pytest.raises(RuntimeError, match="power cut"):
        download_corpus("tiny", progress=False)
    assert _nothing_complete(home)
    assert not [p for p in home.iterdir() if p.name.startswith(".")]
    assert (home / "tiny.zip").read_bytes() == ZIP  # the whole archive is kept
    # the second run unpacks the kept archive: no network needed
    monkeypatch.setattr(download, "_extract_zip", real)
    _register(monkeypatch, "http://127.0.0.1:9/x.zip")
    _assert_whole(download_corpus("tiny", progress=False))


def test_a_corpus_unpacked_meanwhile_by_another_process_is_kept(home, tmp_path, monkeypatch):
    # two processes start on a new machine: both find no corpus and unpack it; the second must
    # not delete the folder the first one finished (and may be reading)
    src = tmp_path / "mirror.zip"
    src.write_bytes(ZIP)
    target = home / "tiny"
    real = download._extract_zip

    def other_process_finishes_first(archive, out):
        real(archive, out)
        monkeypatch.setattr(download, "_extract_zip", real)
        download.unpack(src, target, member=MEMBER, stamp="first")
        (target / "opened.bvh").write_text("in use")

    monkeypatch.setattr(download, "_extract_zip", other_process_finishes_first)
    assert download.unpack(src, target, member=MEMBER, stamp="second") == target
    assert (target / "opened.bvh").read_text() == "in use"
    assert (target / download.DONE).read_text() == "first\n"
    assert {p.name for p in target.glob("*.bvh")} == set(TAKES) | {"opened.bvh"}
    assert not [p for p in home.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_members_escaping_the_folder_are_refused(home, tmp_path, kind):
    members = {"tiny/a.bvh": b"ok", "tiny/../../evil.bvh": b"bad"}
    src = tmp_path / f"evil.{kind}"
    src.write_bytes(_zip_bytes(members) if kind == "zip" else _targz_bytes(members))
    with pytest.raises(DownloadError, match="unsafe member|outside the folder"):
        download.unpack(src, home / "tiny", member="tiny")
    assert not list(tmp_path.rglob("evil.bvh")) and not (home / "tiny").exists()
    with pytest.raises(ValueError, match="relative path"):
        download.unpack(src, home / "tiny", member="../tiny")


def test_the_bundled_corpus_unpacks_without_network_or_falls_back_to_its_url(
    home, tmp_path, monkeypatch
):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "tiny.tar.xz").write_bytes(b"")
    with tarfile.open(bundle / "tiny.tar.xz", "w:xz") as tar:
        for k, v in TAKES.items():
            info = tarfile.TarInfo(f"tiny/{k}")
            info.size = len(v)
            tar.addfile(info, io.BytesIO(v))
    monkeypatch.setattr(corpora, "BUNDLED", bundle)
    _register(monkeypatch, "http://127.0.0.1:9/x.zip", archive="tiny.tar.xz")
    folder = download_corpus("tiny", progress=False)
    assert {p.name: p.read_bytes() for p in folder.glob("*.bvh")} == TAKES
    assert (folder / ".complete").read_text().strip() == "tiny.tar.xz"
    # bundle missing: fetched from the registry's address
    (bundle / "tiny.tar.xz").unlink()
    src = tmp_path / "mirror.zip"
    src.write_bytes(ZIP)
    _register(monkeypatch, src.as_uri(), archive="tiny.tar.xz")
    _assert_whole(download_corpus("tiny", force=True, progress=False))


def test_cli_without_network_says_so_in_one_line(home, monkeypatch, capsys):
    _register(monkeypatch, "http://127.0.0.1:9/x.zip")
    assert main(["data", "download", "tiny", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("minimdm data download: error: cannot reach 127.0.0.1 (")
    assert f"no network? Copy the archive to {home / 'tiny.zip'} and run again" in err
    assert _nothing_complete(home)


def test_cli_list_and_unknown_names(home, tmp_path, monkeypatch, capsys):
    assert main(["data", "list"]) == 0
    out = capsys.readouterr().out
    for name, c in corpora.CORPORA.items():
        row = next(line for line in out.splitlines() if line.startswith(name + " "))
        assert c.licence in row and row.split()[1] == ("bundled" if c.archive else "no")
    assert {"bandai-namco-1", "bandai-namco-2", "lafan1"} <= set(corpora.CORPORA)
    assert str(home) in out
    src = tmp_path / "mirror.zip"
    src.write_bytes(ZIP)
    _register(monkeypatch, src.as_uri())
    assert main(["data", "download", "tiny", "--quiet"]) == 0
    assert main(["data", "list"]) == 0
    out = capsys.readouterr().out
    assert next(ln for ln in out.splitlines() if ln.startswith("tiny ")).split()[1] == "yes"
    assert main(["data", "download", "lafan2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("minimdm data download: error: unknown corpus 'lafan2'")
    assert all(name in err for name in ["bandai-namco-1", "bandai-namco-2", "lafan1"])
