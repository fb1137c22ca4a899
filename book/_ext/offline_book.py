"""A Sphinx extension that keeps the book's pages offline and free of console errors.

jupyter-book 1.x (Sphinx 7.4) adds sphinx-thebe's and sphinx-togglebutton's inline scripts twice
to every page; thebe's declares ``const THEBE_JS_URL`` and so throws "Identifier 'THEBE_JS_URL'
has already been declared". Thebe (live code cells) needs a Binder server and thebe's bundle from
unpkg.com, so an offline book cannot use it: its scripts are dropped, and any other inline script
that appears twice is kept once. The browser test (tests/test_browser.py) checks the result.
"""

from __future__ import annotations

from typing import Any


def _tidy_scripts(app: Any, pagename: str, templatename: str, context: dict, doctree: Any) -> None:
    seen, kept = set(), []
    for js in context.get("script_files", []):
        name = str(getattr(js, "filename", "") or "")
        attrs = getattr(js, "attributes", {}) or {}
        if "thebe" in name or "THEBE" in attrs.get("body", ""):
            continue
        key = (name, tuple(sorted(attrs.items())))
        if key in seen:
            continue
        seen.add(key)
        kept.append(js)
    context["script_files"] = kept


def setup(app: Any) -> dict[str, Any]:
    app.connect("html-page-context", _tidy_scripts, priority=900)  # after the others add theirs
    return {"parallel_read_safe": True, "parallel_write_safe": True}
