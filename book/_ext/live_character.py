"""A Sphinx extension that gives the live character page (live.md) its files.

At the end of an HTML build it copies three.js, the player and ``live.js`` from
``minimdm/viz/static`` into ``_static/live/`` (one copy of each, the package's own) and writes
the joystick policy's graph and start frames there with :func:`minimdm.viz.live.live_bundle`.
ONNX Runtime Web is vendored in ``_vendor/ort`` and so already sits in ``_static/ort``.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any


def _write(app: Any, exception: Exception | None) -> None:
    if exception is not None or app.builder.format != "html":
        return
    from minimdm.viz.live import live_bundle

    static = Path(__file__).resolve().parents[2] / "minimdm" / "viz" / "static"
    out = Path(app.outdir) / "_static" / "live"
    out.mkdir(parents=True, exist_ok=True)
    for name in ("three.module.min.js", "player.js", "live.js"):
        shutil.copy(static / name, out / name)
    live_bundle(out, "rl_joystick")


def setup(app: Any) -> dict[str, Any]:
    app.connect("build-finished", _write)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
