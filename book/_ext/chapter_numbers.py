"""Number exercises per chapter: "Exercise 8.2" is chapter 8's second exercise.

sphinx-exercise numbers its directives with Sphinx's figure counters, which run across the whole
book when the table of contents is not numbered (the chapters carry their numbers in their
titles instead). After Sphinx assigns those numbers, this extension renumbers each chapter's
exercises from 1 and prefixes the chapter's number, taken from the notebook's name
(``notebooks/08_acceleration_ddgan`` is chapter 8). Pages without a chapter number keep theirs.
"""

from __future__ import annotations

import re
from typing import Any

KINDS = ("exercise",)


def _renumber(app: Any, env: Any) -> list[str]:
    for docname, kinds in env.toc_fignumbers.items():
        m = re.match(r"(?:.*/)?(\d+)_", docname)
        if not m:
            continue
        chapter = int(m.group(1))
        for kind in KINDS:
            ids = kinds.get(kind)
            if not ids:
                continue
            for k, key in enumerate(sorted(ids, key=lambda i: ids[i]), start=1):
                ids[key] = (chapter, k)
    return []


def setup(app: Any) -> dict[str, Any]:
    app.connect("env-get-updated", _renumber, priority=900)  # after Sphinx's own numbering
    return {"parallel_read_safe": True, "parallel_write_safe": True}
