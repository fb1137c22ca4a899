"""The live character in a real browser: the joystick policy on A-MDM in ONNX Runtime Web.

A page made of the vendored files only (ONNX Runtime Web's WebAssembly build from
``book/_vendor/ort``, three.js, ``player.js`` and ``live.js``) and a bundle of
:func:`minimdm.viz.live.live_bundle` is served on 127.0.0.1 to Debian's Chromium (Playwright,
offline). The test presses the arrow keys and checks that the root moves in the commanded
direction, reads the page's own frame counter, and that a model file of another kind shows a
readable error instead of a frozen canvas. ``MINIMDM_SCREENSHOTS=folder`` keeps a screenshot of
the page after the key presses. The model runs on its own 30 Hz clock (one frame every 1/30 s of
wall time, drawn at the display's rate); the test checks that pacing, 150 +- 15 frames in 5 s,
which holds wherever one frame of the model takes well under 33 ms (about 7 ms on the 2-core
build machine, busy with two trainings). ``benchmarks/live_page.py`` measures how fast the page
could run.
"""

from __future__ import annotations

import functools
import http.server
import json
import math
import os
import shutil
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STATIC = ROOT / "minimdm" / "viz" / "static"
ORT = ROOT / "book" / "_vendor" / "ort"
PAGE = """<!DOCTYPE html><html><head><meta charset="utf-8"><title>live</title>
<script type="importmap">{"imports": {"three": "./three.module.min.js"}}</script></head>
<body style="max-width:720px;margin:16px auto"><div id="live"></div>
<script type="module">
import * as ort from "./ort/ort.wasm.bundle.min.mjs";
import { live } from "./live.js";
ort.env.wasm.numThreads = 1;
ort.env.wasm.wasmPaths = new URL("./ort/", location.href).href;
live(document.getElementById("live"), { ort, data: "./DATA" }).catch((e) => console.log(e.message));
</script></body></html>"""


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    from minimdm.viz.live import live_bundle

    out = tmp_path_factory.mktemp("live")
    for f in ("three.module.min.js", "player.js", "live.js"):
        shutil.copy(STATIC / f, out / f)
    shutil.copytree(ORT, out / "ort")
    live_bundle(out, "rl_joystick", n_starts=2)
    data = json.loads((out / "rl_joystick.json").read_text())
    data["metadata"]["kind"] = "amdm"  # a model file of another kind
    (out / "wrong.json").write_text(json.dumps(data))
    (out / "index.html").write_text(PAGE.replace("DATA", "rl_joystick.json"))
    (out / "wrong.html").write_text(PAGE.replace("DATA", "wrong.json"))
    handler = functools.partial(_Quiet, directory=str(out))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_port}"
    server.shutdown()


def _open(browser, url):
    page = browser.new_page(viewport={"width": 760, "height": 600})
    errors, outside = [], []
    page.on("console", lambda m: m.type == "error" and errors.append(m.text))
    page.on("pageerror", lambda e: errors.append(str(e)))
    host = url.split("/")[2]
    page.route("**/*", lambda r: r.continue_() if host in r.request.url else (
        outside.append(r.request.url), r.abort()))  # fmt: skip
    page.goto(url)
    return page, errors, outside


def _wait_frames(page, n: int) -> None:
    page.wait_for_function(
        f"Number(document.querySelector('#live').dataset.frames) >= {n}", timeout=120_000
    )


def _state(page):
    return page.eval_on_selector("#live", "e => ({...e.dataset})")


def _steered_run(browser, site) -> dict:
    """One page load: turn the command 90 degrees left, let the policy turn for 10 s of motion,
    then read the heading 10 times over 5 s and measure the walk."""
    page, errors, outside = _open(browser, f"{site}/index.html")
    _wait_frames(page, 30)
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("ArrowLeft")
    f0 = int(_state(page)["frames"])
    _wait_frames(page, f0 + 2)
    goal = float(_state(page)["goal"])
    _wait_frames(page, f0 + 300)
    s1 = _state(page)
    offs = []
    for _ in range(10):
        page.wait_for_timeout(500)
        s = _state(page)
        offs.append(abs(math.remainder(float(s["heading"]) - float(s["goal"]), 2 * math.pi)))
    s2 = _state(page)
    if os.environ.get("MINIMDM_SCREENSHOTS"):  # the page after the key presses
        folder = Path(os.environ["MINIMDM_SCREENSHOTS"])
        folder.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(folder / "live_after_keys.png"))
    page.close()
    dx, dy = float(s2["x"]) - float(s1["x"]), float(s2["y"]) - float(s1["y"])
    return {
        "goal": goal,
        "metres": math.hypot(dx, dy),
        "heading_off": math.degrees(sum(offs) / len(offs)),
        "off": math.degrees(abs(math.remainder(math.atan2(dy, dx) - math.pi / 2, 2 * math.pi))),
        "errors": errors + outside,
    }


def test_the_model_steps_on_its_own_30_hz_clock(browser, site):
    """Frame pacing: the model advances 30 frames per second of wall time, whatever the display's
    rate (150 +- 15 frames in 5 s), and the page's counters say so: its model frames per second
    over the last second, and the speed in the model's own m/s."""
    page, errors, outside = _open(browser, f"{site}/index.html")
    _wait_frames(page, 30)
    f0, t0 = int(_state(page)["frames"]), time.monotonic()
    page.wait_for_timeout(5000)
    s, t1 = _state(page), time.monotonic()
    page.close()
    advanced = (int(s["frames"]) - f0) * 5.0 / (t1 - t0)  # per 5 s of wall time
    print(f"live page: {advanced:.0f} frames in 5 s, counter {s['fps']}/s, {s['speed']} m/s")
    assert 135 <= advanced <= 165, s
    # The page's own counter, over its last second. After a stall the clock catches up by at
    # most 5 periods (live.js resets it beyond that), so one second may hold 30 +- 5 steps:
    # CI's loaded 2-core runner showed 33.3 while 151 frames advanced in 5 s.
    assert 25 <= float(s["fps"]) <= 35, s
    assert 0.05 < float(s["speed"]) < 4.5, s  # m/s in model time: walking, not a blur
    assert not errors and not outside


def test_a_key_press_turns_the_character_to_the_command(browser, site):
    """Two presses of the left arrow turn the command 90 degrees; after 10 s of motion the
    character's heading stays within 15 degrees of it (the mean over 5 s), and its root walks
    that way, within 30 degrees.

    The page draws fresh noise on every load, and the policy misses such a turn now and then:
    in Python, the same scenario from 64 training-take starts missed 15 degrees in 10 runs of 64
    (one ended walking backwards). So the test loads the page up to three times and needs one
    load to settle; every load must set the command and raise no error."""
    runs = []
    for _ in range(3):
        run = _steered_run(browser, site)
        runs.append(run)
        print(f"live page: heading {run['heading_off']:.0f} degrees off the command, "
              f"walking {run['off']:.0f} degrees off it")  # fmt: skip
        assert run["goal"] == pytest.approx(math.pi / 2, abs=1e-3)  # the keys set the command
        assert not run["errors"]
        # it turns and walks that way (1.2 m/s: ~6 m in 5 s)
        if run["heading_off"] < 15 and run["off"] < 30 and run["metres"] > 1.0:
            break
    else:
        raise AssertionError(f"no load of three settled on the command: {runs}")


def test_a_model_file_of_another_kind_shows_a_readable_error(browser, site):
    page, _, outside = _open(browser, f"{site}/wrong.html")
    page.wait_for_selector(".mml-error", timeout=30_000)
    text = page.inner_text(".mml-error")
    assert "cannot start" in text and "model kind amdm" in text
    assert page.query_selector("canvas") is None and not outside
