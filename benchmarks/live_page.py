"""The live character page's pacing in headless Chromium: its model clock against 30 frames/s.

The page of ``tests/test_live.py`` (ONNX Runtime Web's WebAssembly build from ``book/_vendor/ort``,
three.js, ``player.js``, ``live.js`` and the joystick policy's bundle from
:func:`minimdm.viz.live.live_bundle`) is served on 127.0.0.1 to Debian's Chromium (Playwright,
offline), left to run ``--frames`` frames, and its counters are read: the model's frames per
second over the last second (the page paces the model at 30 Hz, so this is at most 30), the
milliseconds one model frame takes (how fast the page could run: 1000 / ms frames/s), the new
frames drawn per second, and frames counted here over 5 s of wall time. The record holds the
machine's load average beside the numbers.

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
import time
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


def page_rates(browser, url: str, frames: int) -> dict:
    """Open the page, let it run ``frames`` frames, count frames over 5 s of wall time, and read
    its own counters."""
    page = browser.new_page(viewport={"width": 760, "height": 600})
    page.goto(url)
    page.wait_for_function(
        f"Number(document.querySelector('#live').dataset.frames) >= {frames}", timeout=600_000
    )
    f0, t0 = int(page.eval_on_selector("#live", "e => e.dataset.frames")), time.monotonic()
    page.wait_for_timeout(5000)
    s = page.eval_on_selector("#live", "e => ({...e.dataset})")
    counted = (int(s["frames"]) - f0) / (time.monotonic() - t0)
    page.close()
    return {
        "model_fps": float(s["fps"]),
        "counted_fps": round(counted, 2),
        "ms_per_frame": float(s["ms"]),
        "drawn_fps": float(s["draws"]),
        "speed_m_s": float(s["speed"]),
    }


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
            runs = [page_rates(browser, url, args.frames) for _ in range(args.runs)]
            browser.close()
        server.shutdown()
    emit(
        {
            "bench": "live_page",
            "frames": args.frames,
            "runs": runs,
            "goal_fps": GOAL_FPS,
            "goal_met": min(r["counted_fps"] for r in runs) >= 0.9 * GOAL_FPS,
            "headroom": round(1000 / max(r["ms_per_frame"] for r in runs) / GOAL_FPS, 2),
            "loadavg_start": load_start,
            "loadavg_end": [round(x, 2) for x in os.getloadavg()],
            **hardware(),
        },
        args.out,
    )


if __name__ == "__main__":
    main()
