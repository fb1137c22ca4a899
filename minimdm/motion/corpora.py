"""Motion corpora: the bundled Bandai-Namco styled mocap, its labels and its fixed split.

The book's models learn from **Bandai-Namco-Research-Motiondataset-1** (Kobayashi et al. 2023,
arXiv:2306.08861; CC BY-NC 4.0, non-commercial use only): 174 BVH takes at 30 fps, 22 joints,
15 styles (normal, happy, sad, angry, proud, not-confident, masculinity, feminine, childish,
old, tired, active, musical, giant, chimpira) over walk, run, dash, walk-back, walk-left,
walk-right and a few gestures. It ships compressed in the project's ``data/`` folder with its
licence, and is unpacked on first use into the data folder (:func:`data_home`).

:func:`load_corpus` returns its takes as :class:`~minimdm.motion.data.Clip` objects carrying
``labels = {"content": ..., "style": ...}``, and splits them by take: no test take is seen in
training. The split is fixed and recorded in ``data/bandai-namco-1.split.json``.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

from minimdm.files import atomic_write

from .bvh import load_bvh
from .data import Clip, MotionDataset
from .download import DONE, DownloadError, fetch, unpack

__all__ = [
    "CORPORA",
    "Corpus",
    "data_home",
    "corpus_path",
    "corpus_split",
    "download_corpus",
    "is_present",
    "list_corpora",
    "load_corpus",
    "load_motion",
]

BUNDLED = Path(__file__).resolve().parents[2] / "data"
"""The project's ``data/`` folder: bundled archives, licences and splits."""


@dataclass(frozen=True)
class Corpus:
    """What the library knows about a corpus."""

    name: str
    """Its name, as given to :func:`load_corpus` and ``minimdm data``."""
    description: str
    """One line on what it holds."""
    licence: str
    """Its licence, in short."""
    attribution: str
    """Who made it and what to cite."""
    archive: str
    """File name of the bundled archive in ``data/`` ('' if it is not bundled)."""
    folder: str
    """The folder inside the bundled archive, and the corpus's folder in the data folder."""
    url: str = ""
    """Where ``minimdm data download`` fetches it ('' if nowhere)."""
    member: str = ""
    """The folder inside the downloaded archive that becomes the corpus ('' = its root)."""
    size: int | None = None
    """Bytes of the downloaded archive, or None when unknown (then not checked)."""
    sha256: str | None = None
    """SHA-256 of the downloaded archive, or None when unknown (then trusted on first use)."""
    scale: float | None = None
    """File units -> metres when the corpus documents its units; None guesses per take."""


# The Bandai-Namco corpora come from GitHub's archive of the whole repository's main branch
# (github.com/<owner>/<repo>/archive/refs/heads/main.zip): one stable address with no release
# to pin, whose zip holds everything under "<repo>-main/". It changes whenever upstream commits,
# so its size and hash are unknown here (None) and trusted on first use. LaFAN1's BVH files are
# one Git-LFS zip; we use its "raw" address, which GitHub redirects to the LFS media server
# (media.githubusercontent.com) -- the raw address stays valid if the media host changes.
# None of these addresses could be tried from the machine that wrote this (no network).
_BANDAI_REPO = "BandaiNamcoResearchInc/Bandai-Namco-Research-Motiondataset"
_BANDAI_ZIP = f"https://github.com/{_BANDAI_REPO}/archive/refs/heads/main.zip"
_BANDAI_ROOT = "Bandai-Namco-Research-Motiondataset-main/dataset"

LOCOMOTION = ("walk", "walk-back", "walk-left", "walk-right", "run", "dash")
"""The locomotion contents of the Bandai-Namco corpora (their ``content`` label), in the order
tables print them."""

CORPORA: dict[str, Corpus] = {
    "bandai-namco-1": Corpus(
        name="bandai-namco-1",
        description="174 takes, 30 fps, 22 joints, 15 styles of locomotion and gestures",
        licence="CC BY-NC 4.0 (non-commercial use only)",
        attribution="Bandai Namco Research Inc.; Kobayashi et al. 2023, arXiv:2306.08861",
        archive="bandai-namco-1.tar.xz",
        folder="bandai-namco-1",
        url=_BANDAI_ZIP,
        member=f"{_BANDAI_ROOT}/Bandai-Namco-Research-Motiondataset-1",
        scale=0.01,  # centimetres; a per-take guess scales crouched or leaning takes wrongly
    ),
    "bandai-namco-2": Corpus(
        name="bandai-namco-2",
        description="2,902 takes, 384,931 frames, 30 fps, 7 styles: locomotion incl. turns, "
        "hand actions (~515 MB of BVH)",
        licence="CC BY-NC 4.0 (non-commercial use only)",
        attribution="Bandai Namco Research Inc.; Kobayashi et al. 2023, arXiv:2306.08861",
        archive="",
        folder="bandai-namco-2",
        url=_BANDAI_ZIP,
        member=f"{_BANDAI_ROOT}/Bandai-Namco-Research-Motiondataset-2",
        scale=0.01,  # centimetres, as dataset 1
    ),
    "lafan1": Corpus(
        name="lafan1",
        description="Ubisoft La Forge Animation Dataset: 77 BVH takes, 30 fps, 5 subjects",
        licence="CC BY-NC-ND 4.0 (non-commercial, no derivatives)",
        attribution="Ubisoft La Forge; Harvey et al. 2020, Robust Motion In-betweening",
        archive="",
        folder="lafan1",
        url="https://github.com/ubisoft/ubisoft-laforge-animation-dataset/raw/master/lafan1/lafan1.zip",
        member="lafan1",
    ),
}
"""The known corpora, by name."""


def _known(name: str) -> Corpus:
    if name not in CORPORA:
        raise ValueError(f"unknown corpus {name!r}; known corpora: {sorted(CORPORA)}")
    return CORPORA[name]


def data_home() -> Path:
    """Where corpora are unpacked: ``$MINIMDM_DATA``, else the platform's cache folder."""
    if os.environ.get("MINIMDM_DATA"):
        return Path(os.environ["MINIMDM_DATA"]).expanduser()
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local"))
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "minimdm"


_DONE = DONE  # written last: a folder without it is a partial extraction


def is_present(name: str) -> bool:
    """True when the corpus is unpacked whole (its ``.complete`` marker) in :func:`data_home`."""
    return (data_home() / _known(name).folder / _DONE).exists()


def corpus_path(name: str) -> Path:
    """The folder of an unpacked corpus, unpacking the bundled archive on first use.

    Unpacking goes to a temporary folder beside the target and is renamed into place when
    complete, so an interrupted run never leaves a half-extracted corpus that looks whole.
    """
    info = _known(name)
    target = data_home() / info.folder
    if (target / _DONE).exists():
        return target
    archive = BUNDLED / info.archive
    if not info.archive or not archive.exists():
        fix = f"; run `minimdm data download {name}`" if info.url else ""
        raise FileNotFoundError(
            f"corpus {name!r} is not unpacked in {target} and has no bundled archive{fix}"
        )
    return unpack(archive, target, member=info.folder, stamp=info.archive)


def _archive_name(name: str, url: str) -> str:
    """``NAME`` plus the archive suffix of ``url`` (``.zip``, ``.tar.gz``, ...)."""
    path = urllib.parse.urlsplit(url).path.lower()
    for suffix in (".tar.gz", ".tgz", ".tar.bz2", ".tar.xz", ".tar", ".zip"):
        if path.endswith(suffix):
            return name + suffix
    return name + ".archive"  # unpack() tells zip from tar by content, not by name


def download_corpus(
    name: str, *, force: bool = False, url: str | None = None, progress: bool = True
) -> Path:
    """Download and unpack a corpus into :func:`data_home`; return its folder.

    A bundled corpus is unpacked from ``data/`` (no network) unless ``url`` is given. Otherwise
    the archive goes to ``data_home()/NAME.zip`` (or ``.tar.gz``, ...) via ``NAME.zip.part``,
    which a later run resumes; copying the archive there by hand skips the download. The
    archive is deleted once unpacked.

    The archive's size and SHA-256 are checked when :data:`CORPORA` records them. When it does
    not (None: unknown), the SHA-256 of what arrived is printed and recorded in
    ``data_home()/NAME.sha256`` once the archive has unpacked; later downloads must match it
    (trust on first use; delete that
    file to accept a new upstream version).

    Args:
        name: a corpus of :data:`CORPORA`.
        force: download and unpack again even if the corpus is present.
        url: fetch from here instead (a mirror, or a ``file://`` path).
        progress: show a progress bar.

    Raises:
        ValueError: an unknown name (listing the known ones).
        DownloadError: no network (one line: what to do), or a size/hash mismatch.
    """
    info = _known(name)
    home = data_home()
    target = home / info.folder
    if force and target.exists():
        shutil.rmtree(target)
    if (target / _DONE).exists():
        return target
    if url is None and info.archive and (BUNDLED / info.archive).exists():
        return corpus_path(name)
    source = url or info.url
    if not source:
        raise ValueError(f"corpus {name!r} has no download address")
    archive = home / _archive_name(name, source)
    record = home / f"{name}.sha256"
    trusted = record.read_text().split()[0] if info.sha256 is None and record.exists() else None
    try:
        digest = fetch(
            source, archive, size=info.size, sha256=info.sha256 or trusted, progress=progress
        )
    except DownloadError as e:
        if trusted and "SHA-256" in str(e):
            raise DownloadError(
                f"{e} (recorded in {record} on first download; delete that "
                "file if upstream changed)"
            ) from None
        raise
    try:
        unpack(archive, target, member=info.member, stamp=f"{source} sha256={digest}")
    except DownloadError as e:  # not an archive, or not the one expected: trust nothing
        archive.unlink(missing_ok=True)
        raise DownloadError(f"{e}; deleted {archive.name}, recorded no SHA-256") from None
    if info.sha256 is None and trusted is None:  # trusted only once it unpacked
        atomic_write(record, f"{digest}  {source}\n")
        print(f"{archive.name}: SHA-256 {digest} (unknown to minimdm; recorded in {record})")
    archive.unlink()
    return target


def list_corpora() -> list[dict[str, str]]:
    """One row per corpus: name, description, licence and whether it is in :func:`data_home`."""
    return [
        {
            "corpus": c.name,
            "present": "yes" if is_present(c.name) else ("bundled" if c.archive else "no"),
            "licence": c.licence,
            "description": c.description,
        }
        for c in CORPORA.values()
    ]


def corpus_split(name: str) -> dict[str, list[str]]:
    """The fixed split by take: ``{"train": [...], "test": [...]}`` of take names."""
    info = _known(name)
    path = BUNDLED / f"{info.folder}.split.json"
    rec = json.loads(path.read_text())
    takes = sorted(p.stem for p in (corpus_path(name) / "data").glob("*.bvh"))
    test = sorted(rec["test"])
    missing = sorted(set(test) - set(takes))
    if missing:
        raise ValueError(f"{path}: test takes {missing[:3]} are not in corpus {name!r}")
    return {"train": [t for t in takes if t not in set(test)], "test": test}


def _label_names(folder: Path, kind: str) -> list[str]:
    """Label names of ``cfg/{kind}_label.txt`` (line i is label i), prefix ``dataset-1_`` cut."""
    lines = (folder / "cfg" / f"{kind}_label.txt").read_text().split()
    return [ln.split("_", 1)[1] if "_" in ln else ln for ln in lines]


def _labels(folder: Path, take: str, contents: list[str], styles: list[str]) -> dict[str, str]:
    """The take's labels from its JSON, checked against its file name."""
    path = folder / "data" / f"{take}.json"
    if not path.exists():
        raise FileNotFoundError(f"{path}: the label file of {take}.bvh is missing")
    rec = json.loads(path.read_text())
    try:
        labels = {"content": contents[rec["content"]], "style": styles[rec["style"]]}
    except (KeyError, IndexError, TypeError):
        raise ValueError(
            f"{path}: expected {{'content': 0..{len(contents) - 1}, 'style': 0..{len(styles) - 1}}}"
            f", got {rec!r}"
        ) from None
    # dataset-1_{content}_{style}_{id}: content and style may hold '-' but never '_'
    _, content, style, _ = take.split("_")
    if (content, style) != (labels["content"], labels["style"]):
        raise ValueError(
            f"{path}: labels {labels} do not match the take's name {take}.bvh "
            f"(content {content!r}, style {style!r})"
        )
    return labels


def load_corpus(
    name: str = "bandai-namco-1",
    split: str | None = None,
    fps: float = 30.0,
    takes: list[str] | None = None,
) -> MotionDataset:
    """The takes of a corpus as labelled clips.

    Args:
        name: a corpus of :data:`CORPORA`.
        split: ``"train"``, ``"test"`` or None (every take).
        fps: resample to this rate.
        takes: only these takes (names without ``.bvh``), e.g. for a quick look.

    Returns:
        A :class:`~minimdm.motion.data.MotionDataset` of clips named after their takes, each
        with ``labels = {"content": ..., "style": ...}``.
    """
    info = _known(name)
    if split not in (None, "train", "test"):
        raise ValueError(f"split must be 'train', 'test' or None, got {split!r}")
    folder = corpus_path(name)
    if not (folder / "cfg" / "content_label.txt").exists():  # no Bandai-style labels
        if split is not None and not (BUNDLED / f"{info.folder}.split.json").exists():
            raise ValueError(f"corpus {name!r} has no fixed split; use split=None")
        dataset = load_bvh(folder, fps=fps, scale=info.scale)
        keep = _only(dataset.names, takes, f"corpus {name!r}")
        return MotionDataset([c for c in dataset if c.name in set(keep)])
    names = sorted(p.stem for p in (folder / "data").glob("*.bvh"))
    if split is not None:
        names = corpus_split(name)[split]
    names = _only(names, takes, f"corpus {name!r} (split {split})")
    contents, styles = _label_names(folder, "content"), _label_names(folder, "style")
    clips: list[Clip] = []
    for take in names:
        clip = load_bvh(folder / "data" / f"{take}.bvh", fps=fps, scale=info.scale)
        clip.labels = _labels(folder, take, contents, styles)
        clips.append(clip)
    return MotionDataset(clips)


def load_motion(
    source: str,
    split: str | None = None,
    fps: float = 30.0,
    names: list[str] | None = None,
    loop_frames: int | None = None,
) -> MotionDataset:
    """The clips a training config names: ``"deepmimic"``, a corpus name, or a BVH folder.

    Args:
        source: ``"deepmimic"`` (the 20 DeepMimic clips of ``pybullet_data``), a name of
            :data:`CORPORA` (bundled or downloaded with ``minimdm data download``), or the path
            of a folder of ``.bvh`` files (one skeleton; see :func:`~minimdm.motion.bvh.load_bvh`).
        split: ``"train"`` or ``"test"`` takes of a corpus's fixed split, or None (all). A BVH
            folder and the DeepMimic clips have no split.
        fps: resample to this rate.
        names: only these clips or takes (None: all of them).
        loop_frames: unroll looping clips to this many frames (DeepMimic only; corpora's takes
            do not loop).
    """
    from .data import load_clips

    if source == "deepmimic":
        if split is not None:
            raise ValueError(f"the DeepMimic clips have no split; use split: null, got {split!r}")
        return load_clips(fps=fps, loop_frames=loop_frames, names=names)
    if source in CORPORA:
        return load_corpus(source, split=split, fps=fps, takes=names)
    path = Path(source).expanduser()
    if not path.is_dir():
        raise ValueError(
            f"data source {source!r} is neither 'deepmimic', a known corpus "
            f"({sorted(CORPORA)}) nor a folder of .bvh files"
        )
    if split is not None:
        raise ValueError(f"a BVH folder has no fixed split; use split: null, got {split!r}")
    dataset = load_bvh(path, fps=fps)
    keep = _only(dataset.names, names, str(path))
    return MotionDataset([c for c in dataset if c.name in set(keep)])


def _only(have: list[str], wanted: list[str] | None, where: str) -> list[str]:
    """The names of ``have`` that are ``wanted`` (all when None), in ``have``'s order; a wanted
    name that is missing is an error naming ``where``."""
    if wanted is None:
        return list(have)
    unknown = sorted(set(wanted) - set(have))
    if unknown:
        raise ValueError(f"takes {unknown[:3]} are not in {where}")
    return [n for n in have if n in set(wanted)]
