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
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

from .bvh import load_bvh
from .data import Clip, MotionDataset

__all__ = ["CORPORA", "Corpus", "data_home", "corpus_path", "corpus_split", "load_corpus"]

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
    """The folder inside the archive (and in the data folder) that holds the corpus."""


CORPORA: dict[str, Corpus] = {
    "bandai-namco-1": Corpus(
        name="bandai-namco-1",
        description="174 takes, 30 fps, 22 joints, 15 styles of locomotion and gestures",
        licence="CC BY-NC 4.0 (non-commercial use only)",
        attribution="Bandai Namco Research Inc.; Kobayashi et al. 2023, arXiv:2306.08861",
        archive="bandai-namco-1.tar.xz",
        folder="bandai-namco-1",
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


_DONE = ".complete"  # written last: a folder without it is a partial extraction


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
        raise FileNotFoundError(
            f"corpus {name!r} is not unpacked in {target} and its archive {archive} is missing"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{info.folder}-", dir=target.parent))
    try:
        with tarfile.open(archive) as tar:
            tar.extractall(tmp, filter="data")
        unpacked = tmp / info.folder
        if not unpacked.is_dir():
            raise FileNotFoundError(f"{archive} holds no folder {info.folder!r}")
        (unpacked / _DONE).write_text(info.archive + "\n")
        if target.exists():  # a partial folder from an earlier, interrupted attempt
            shutil.rmtree(target)
        os.replace(unpacked, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


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
    _known(name)
    if split not in (None, "train", "test"):
        raise ValueError(f"split must be 'train', 'test' or None, got {split!r}")
    folder = corpus_path(name)
    names = sorted(p.stem for p in (folder / "data").glob("*.bvh"))
    if split is not None:
        names = corpus_split(name)[split]
    if takes is not None:
        unknown = sorted(set(takes) - set(names))
        if unknown:
            raise ValueError(f"takes {unknown[:3]} are not in corpus {name!r} (split {split})")
        names = [n for n in names if n in set(takes)]
    contents, styles = _label_names(folder, "content"), _label_names(folder, "style")
    clips: list[Clip] = []
    for take in names:
        clip = load_bvh(folder / "data" / f"{take}.bvh", fps=fps)
        clip.labels = _labels(folder, take, contents, styles)
        clips.append(clip)
    return MotionDataset(clips)
