"""The live character page's frame rate in headless Chromium, against issue 16's goal of 30 fps.

The page of ``tests/test_live.py`` (ONNX Runtime Web's WebAssembly build from ``book/_vendor/ort``,
three.js, ``player.js``, ``live.js`` and the joystick policy's bundle from
:func:`minimdm.viz.live.live_bundle`) is served on 127.0.0.1 to Debian's Chromium (Playwright,
offline), left to run ``--frames`` frames, and its own frame counter is read. This is a timing, so
it lives here and not in the tests: on a busy machine the page runs slower. The record holds the
machine's load average beside the rate.

    python benchmarks/live_page.py               # about a minute on the 2-core build machine
    python benchmarks/live_page.py --runs 3      # three page loads

Prints JSON lines and appends them to ``benchmarks/results/live_page.jsonl``.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import os
import shutil
import tempfile
import threading
from pathlib import Path

from common import ROOT, emit, hardware

GOAL_FPS = 30.0
CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update"]  # fmt: skip
PAGE = """<!DOCTYPE html><html><head><meta charset="utf-8"><title>live</title>
<script type="importmap">{"imports": {"three": "./three.module.min.js"}}</script></head>
<body style="max-width:720px;margin:16px auto"><div id="live"></div>
<script type="module">
import * as ort from "./ort/ort.wasm.bundle.min.mjs";
import { live } from "./live.js";
ort.env.wasm.numThreads = 1;
ort.env.wasm.wasmPaths = new URL("./ort/", location.href).href;
live(document.getElementById("live"), { ort, data: "./rl_joystick.json" });
</script></body></html>"""


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def build_site(out: Path) -> None:
    """The page and everything it loads, in folder ``out``."""
    from minimdm.viz.live import live_bundle

    static = ROOT / "minimdm" / "viz" / "static"
    for f in ("three.module.min.js", "player.js", "live.js"):
        shutil.copy(static / f, out / f)
    shutil.copytree(ROOT / "book" / "_vendor" / "ort", out / "ort")
    live_bundle(out, "rl_joystick", n_starts=2)
    (out / "index.html").write_text(PAGE)


def page_fps(browser, url: str, frames: int) -> float:
    """Open the page, let it run ``frames`` frames, and read its own counter (frames/s)."""
    page = browser.new_page(viewport={"width": 760, "height": 600})
    page.goto(url)
    page.wait_for_function(
        f"Number(document.querySelector('#live').dataset.frames) >= {frames}", timeout=600_000
    )
    fps = float(page.eval_on_selector("#live", "e => e.dataset.fps"))
    page.close()
    return fps


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=600, help="frames per page load (20 s at 30 fps)")
    p.add_argument("--runs", type=int, default=1, help="page loads")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "live_page.jsonl"))
    args = p.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp:
        build_site(Path(tmp))
        handler = functools.partial(_Quiet, directory=tmp)
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        url = f"http://127.0.0.1:{server.server_port}/index.html"
        load_start = [round(x, 2) for x in os.getloadavg()]
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
            rates = [page_fps(browser, url, args.frames) for _ in range(args.runs)]
            browser.close()
        server.shutdown()
    emit(
        {
            "bench": "live_page",
            "frames": args.frames,
            "fps": rates,
            "goal_fps": GOAL_FPS,
            "goal_met": min(rates) >= GOAL_FPS,
            "loadavg_start": load_start,
            "loadavg_end": [round(x, 2) for x in os.getloadavg()],
            **hardware(),
        },
        args.out,
    )


if __name__ == "__main__":
    main()
