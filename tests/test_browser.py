"""The book and the 3D player in a real browser: Debian's Chromium, driven by Playwright, offline.

The test builds the real book (into a temporary folder) and adds a page with two players made
by :func:`minimdm.viz.player`, serves the folder on 127.0.0.1 and checks, on every page: no
console error, no request outside the book (requests elsewhere are blocked and recorded), and
rendered maths (``mjx-container`` elements, no raw ``\\(``) on the chapters. On the player page:
the canvases are not blank, scrubbing or turning one player changes its picture and not the
other's, and a page holding only a later player (no code of its own) still works from the copy
the first one left in the browser. On every chapter page that carries players, each one mounts
(its poster gives way) and draws a picture that is not blank.

It needs Chromium (``apt-get install -y chromium``; Playwright's own browser download is never
used) and is skipped without it, except in CI (``CI=true``), where it fails instead.
Set ``MINIMDM_SCREENSHOTS=folder`` to keep screenshots of the pages it looked at.
"""

from __future__ import annotations

import functools
import http.server
import io
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import _unavailable

ROOT = Path(__file__).resolve().parents[1]
# How long a page may take to mount its players. Chromium draws WebGL on the CPU here
# (SwiftShader): chapter 2's 14 players take about 9 s of compiling and context set-up on an idle
# 2-core machine, and several times that beside other work.
PAGE_TIMEOUT = 120_000


def two_players() -> tuple[str, str]:
    """Two players of real motion: two walks side by side, and a run with keyframes."""
    from minimdm import viz
    from minimdm.motion.corpora import load_corpus

    corpus = load_corpus("bandai-namco-1")
    sk = corpus["dataset-1_walk_normal_001"].skeleton  # offsets differ by take; parents do not
    a, b = (corpus[f"dataset-1_walk_{s}_001"].positions[:90] for s in ("normal", "happy"))
    run = corpus["dataset-1_run_normal_001"].positions  # 24 frames
    first = viz.player(
        [a, b], sk, labels=["normal", "happy"], targets=[[2.5, 0.0]], autoplay=False, embed=True
    )
    second = viz.player(
        run,
        sk,
        labels=["run"],
        layout="overlay",
        keyframes={"frames": [len(run) - 1], "poses": run[-1:]},
        paths=run[:, 0, :2],
        follow=True,
        autoplay=False,
        embed=False,  # waits for the first one's code
    )
    return first._repr_html_(), second._repr_html_()


def page(title: str, body: str) -> str:
    return (
        f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{title}</title></head>'
        '<body style="font-family:sans-serif;max-width:720px;margin:16px auto">'
        f"{body}</body></html>"
    )


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The built book plus two player pages, served on 127.0.0.1; yields (base URL, folder)."""
    out = tmp_path_factory.mktemp("book")
    jb = shutil.which("jupyter-book") or str(Path(sys.executable).with_name("jupyter-book"))
    if not Path(jb).exists():
        _unavailable("jupyter-book is not installed (pip install -e '.[book]')")
    run = subprocess.run(
        [jb, "build", str(ROOT / "book"), "--path-output", str(out), "--warningiserror"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    html = out / "_build" / "html"
    first, second = two_players()
    (html / "players.html").write_text(page("players", f"<h1>Players</h1>{first}{second}"))
    (html / "later_only.html").write_text(page("later only", second))
    handler = functools.partial(Quiet, directory=str(html))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}/", html
    server.shutdown()


class Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


class Visit:
    """A page in a fresh browser context: console errors and requests outside the site."""

    def __init__(self, browser, base: str, context=None):
        self.base, self.errors, self.outside = base, [], []
        self.context = context or browser.new_context(viewport={"width": 1000, "height": 900})
        self.context.set_default_timeout(PAGE_TIMEOUT)
        self.context.route("**/*", self._route)
        self.page = self.context.new_page()
        self.page.on("console", lambda m: m.type == "error" and self.errors.append(m.text))
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        # a request the browser cancels itself (net::ERR_ABORTED: the favicon of a page it leaves
        # for the next) is no error; those outside the book fail as net::ERR_FAILED (_route)
        self.page.on(
            "requestfailed",
            lambda r: (
                "ERR_ABORTED" in (r.failure or "") or self.errors.append(f"{r.failure}: {r.url}")
            ),
        )

    def _route(self, route):
        url = route.request.url
        if url.startswith((self.base, "blob:", "data:")):
            route.continue_()
        else:
            self.outside.append(url)
            route.abort()

    def open(self, path: str):
        self.page.goto(self.base + path, wait_until="load")
        return self.page

    def check_clean(self):
        assert self.outside == [], f"requests outside the book: {self.outside}"
        assert self.errors == [], f"console errors: {self.errors}"


def shot(locator) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(locator.screenshot())).convert("L"), dtype=float)


def keep(page, name: str, full_page: bool = True) -> None:
    folder = os.environ.get("MINIMDM_SCREENSHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(folder) / f"{name}.png"), full_page=full_page)


def settle(page) -> None:
    """Wait for two animation frames, so that what was asked is drawn."""
    page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")


def test_two_players_on_one_page(browser, site):
    base, _ = site
    v = Visit(browser, base)
    p = v.open("players.html")
    p.wait_for_function(
        "document.querySelectorAll('.minimdm-player[data-ready=\"1\"]').length === 2",
        timeout=PAGE_TIMEOUT,
    )
    players = p.locator(".minimdm-player")
    assert players.locator(".mmp-poster").count() == 0  # the posters gave way to the canvases
    assert not players.locator(".mmp-msg").first.is_visible()  # and so did the still's note
    a, b = (players.nth(i).locator("canvas") for i in (0, 1))

    def scrub(i: int, frame: int) -> None:
        players.nth(i).locator("input[type=range]").evaluate(
            "(s, f) => { s.value = f; s.dispatchEvent(new Event('input', {bubbles: true})); }",
            frame,
        )
        p.wait_for_function(
            f"document.querySelectorAll('.minimdm-player')[{i}].dataset.frame === '{frame}'"
        )
        settle(p)

    scrub(0, 0)
    scrub(1, 0)
    a0, b0 = shot(a), shot(b)
    for img in (a0, b0):  # not blank: skeletons, grid and shadows on the ground
        assert img.std() > 8, img.std()
    keep(p, "players")
    scrub(0, 60)
    a1, b1 = shot(a), shot(b)
    assert np.abs(a1 - a0).mean() > 0.5  # the picture moved ...
    assert np.abs(b1 - b0).mean() < 0.05  # ... in the player scrubbed, not in the other
    assert players.nth(0).locator(".mmp-time").inner_text().startswith("61 / 90")
    box = b.bounding_box()  # turn the second player by dragging
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    p.mouse.move(cx, cy)
    p.mouse.down()
    p.mouse.move(cx + 120, cy + 10, steps=5)
    p.mouse.up()
    settle(p)
    assert np.abs(shot(b) - b1).mean() > 0.5
    assert np.abs(shot(a) - a1).mean() < 0.05
    players.nth(1).locator("button[title^='play']").click()  # and it plays
    p.wait_for_function("document.querySelectorAll('.minimdm-player')[1].dataset.frame !== '0'")
    v.check_clean()
    # a page holding only the later player: no code of its own, so it takes the copy that the
    # first player left in this browser's localStorage
    later = v.context.new_page()
    later.goto(base + "later_only.html")
    later.wait_for_selector(".minimdm-player[data-ready='1']", timeout=PAGE_TIMEOUT)
    v.check_clean()
    v.context.close()


def test_later_player_alone_in_a_new_browser_keeps_its_poster(browser, site):
    base, _ = site
    v = Visit(browser, base)
    p = v.open("later_only.html")
    msg = p.locator(".mmp-msg")
    msg.wait_for(state="visible", timeout=15_000)
    assert "not on this page" in msg.inner_text()
    assert p.locator("img.mmp-poster").count() == 1
    v.check_clean()
    v.context.close()


# Every output area (text and HTML) that scrolls sideways, and every figure shown below 80% of
# its own width (a PNG's width attribute, else its pixels), on a chapter page.
LAYOUT = """() => {
  const wide = [], small = [];
  document.querySelectorAll('.cell_output pre, .cell_output .output.text_html').forEach((e) => {
    if (e.closest('.minimdm-player')) return;
    if (e.scrollWidth > e.clientWidth + 1) {
      const line = (e.innerText || '').split('\\n').find((l) => l.trim()) || '';
      wide.push(`${e.scrollWidth} px > ${e.clientWidth} px: ${line.trim().slice(0, 50)}`);
    }
  });
  document.querySelectorAll('.cell_output img:not(.mmp-poster)').forEach((img) => {
    const own = Number(img.getAttribute('width')) || img.naturalWidth;
    const shown = img.getBoundingClientRect().width;
    if (own && shown < 0.8 * own) small.push(`${Math.round(shown)} of ${own} px: ${img.alt}`);
  });
  return { column: document.querySelector('article').clientWidth, wide, small };
}"""


MATHS_PAGES = ("notation.html", "glossary.html")  # besides the chapters
OTHER_PAGES = ["intro.html", "notation.html", "glossary.html", "bibliography.html"]


@pytest.fixture(scope="module")
def walk(browser, site) -> dict[str, dict]:
    """Every page of the book, each opened once at a 1280-pixel window (a 688-pixel text column),
    with what the tests below read from it: console errors and requests outside the book, the
    rendered maths and any raw TeX left in the prose, and on a chapter page its players, its
    layout and its exercise solutions. Walking once serves all of them: on a CPU, mounting a
    page's WebGL players is most of the time a visit takes."""
    base, html = site
    chapters = sorted(str(f.relative_to(html)) for f in (html / "notebooks").glob("*.html"))
    v, seen = Visit(browser, base, browser.new_context(viewport={"width": 1280, "height": 900})), {}
    for name in chapters + OTHER_PAGES:
        p, rec = v.open(name), {}
        if name in chapters or name in MATHS_PAGES:
            rec |= read_maths(p)
        if name in chapters:
            p.wait_for_function("[...document.images].every(i => i.complete)")
            rec["layout"] = p.evaluate(LAYOUT)
            rec |= read_players(p, name)
            rec["solutions"] = read_solutions(p, name)
        if name.endswith("03_amdm.html"):
            keep(p, "chapter3", full_page=False)
        rec["errors"], rec["outside"] = list(v.errors), list(v.outside)
        v.errors.clear()
        v.outside.clear()
        seen[name] = rec
    v.context.close()
    return seen


def read_maths(p) -> dict:
    """How many formulas MathJax rendered, and which raw TeX delimiters are left in the prose."""
    p.wait_for_function("window.MathJax && MathJax.startup && MathJax.startup.promise")
    p.evaluate("MathJax.startup.promise.then(() => document.fonts.ready).then(() => 1)")
    prose = p.evaluate(
        """() => { const a = document.querySelector('article').cloneNode(true);
        a.querySelectorAll('pre, code, .cell_input, .cell_output').forEach(e => e.remove());
        return a.innerText; }"""
    )
    raw = [r for r in ("\\(", "\\[", "$$") if r in prose]
    return {"maths": p.locator("mjx-container").count(), "raw_tex": raw}


def read_players(p, name: str) -> dict:
    """Every player on a chapter page: it mounts (its poster gives way), draws a picture that is
    not blank, keeps its labels inside it, and shows its characters (the share of the picture's
    height, at the first and the middle frame). Each is paused first, so that the page's players
    do not all play at once."""
    players, problems, heights = p.locator(".minimdm-player"), [], {}
    n = players.count()
    if n == 0:
        return {"players": 0, "player_problems": [], "heights": {}}
    p.wait_for_function(
        f"document.querySelectorAll('.minimdm-player[data-ready=\"1\"]').length === {n}",
        timeout=PAGE_TIMEOUT,
    )
    for i in range(n):  # scrubbing pauses a player
        players.nth(i).locator("input[type=range]").evaluate(
            "s => { s.value = 0; s.dispatchEvent(new Event('input', {bubbles: true})); }"
        )
    if players.locator(".mmp-poster").count():
        problems.append(f"{name}: a poster was not replaced")
    folder = os.environ.get("MINIMDM_SCREENSHOTS")
    for i in range(n):
        players.nth(i).scroll_into_view_if_needed()
        settle(p)
        img = shot(players.nth(i).locator("canvas"))
        if img.std() <= 8:
            problems.append(f"{name}: player {i} looks blank (std {img.std():.1f})")
        cut = players.nth(i).evaluate(
            """e => { const c = e.querySelector('canvas').getBoundingClientRect();
            return [...e.querySelectorAll('.mmp-label')]
              .filter(l => l.textContent && l.style.visibility !== 'hidden')
              .filter(l => { const r = l.getBoundingClientRect();
                             return r.top < c.top - 1 || r.bottom > c.bottom + 1; })
              .map(l => l.textContent); }"""
        )
        if cut:
            problems.append(f"{name}: player {i} cuts off its labels {cut}")
        if folder:
            Path(folder).mkdir(parents=True, exist_ok=True)
            players.nth(i).screenshot(path=str(Path(folder) / f"{Path(name).stem}_player{i}.png"))
        for at in ("0", "Math.floor(pl.nFrames / 2)"):
            js = f"e => {{ const pl = e.minimdmPlayer; pl.setFrame({at}); "
            js += "return pl.bodyHeights(); }"
            heights[f"{name} player {i} frame {at[:1]}"] = players.nth(i).evaluate(js)
    return {"players": n, "player_problems": problems, "heights": heights}


def read_solutions(p, name: str) -> dict | None:
    """A page's sphinx-exercise solutions (None where it has none): how many exercises and
    solutions, which solutions show before any click, and whether the first one opens with its
    toggle button."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    solutions = p.locator("div.solution")
    if solutions.count() == 0:
        return None
    p.wait_for_selector("div.solution button.toggle-button", state="attached")
    shown = [
        i
        for i in range(solutions.count())
        if solutions.nth(i).locator("section#solution-content").is_visible()
    ]
    first = solutions.nth(0)
    first.scroll_into_view_if_needed()
    first.locator("button.toggle-button").click()
    body = first.locator("section#solution-content")
    try:
        body.wait_for(state="visible", timeout=15_000)
        opens = True
    except PlaywrightTimeout:  # the click did not unfold it
        opens = False
    if name.endswith("08_acceleration_ddgan.html"):
        keep(p, "chapter8_solution_open", full_page=False)
    n_ex = p.locator("div.exercise").count()
    return {"exercises": n_ex, "solutions": solutions.count(), "shown": shown, "opens": opens}


def test_book_pages_are_offline_and_render_maths(walk):
    """No page logs a console error or asks for anything outside the book; the chapters, the
    notation and the glossary render their maths and leave no raw TeX in the prose."""
    assert len(walk) >= 8
    for name, rec in walk.items():
        assert rec["outside"] == [], f"{name}: requests outside the book: {rec['outside']}"
        assert rec["errors"] == [], f"{name}: console errors: {rec['errors']}"
        if "maths" in rec:
            assert rec["maths"] > 0, f"{name}: no rendered maths"
            assert rec["raw_tex"] == [], f"{name}: raw TeX {rec['raw_tex']} in the text"


def test_chapter_players_mount_and_draw(walk):
    """Every player on every chapter page mounts, draws a picture that is not blank and keeps
    its labels inside it."""
    n_players = sum(rec.get("players", 0) for rec in walk.values())
    assert n_players >= 4, f"only {n_players} players in the chapters"
    problems = [msg for rec in walk.values() for msg in rec.get("player_problems", [])]
    assert problems == [], "\n".join(problems)


def test_chapter_outputs_fit_the_column(walk):
    """On every chapter page, at a 1280-pixel window (a 688-pixel text column): no output
    scrolls sideways, no figure is shrunk below 80% of its width, and each player's default
    camera shows its characters at least about a third of the picture's height (at the first
    and the middle frame)."""
    problems, heights = [], {}
    for name, rec in walk.items():
        if "layout" not in rec:
            continue
        r = rec["layout"]
        assert r["column"] == 752, r["column"]  # the article; its code areas are 688 px
        problems += [f"{name}: wide output {w}" for w in r["wide"]]
        problems += [f"{name}: shrunk figure {s}" for s in r["small"]]
        heights |= rec["heights"]
    for where, h in heights.items():
        if sum(h) / len(h) < 0.3:
            problems.append(f"{where} shows its characters {h} of its height")
    assert len(heights) >= 8, heights
    assert problems == [], "\n".join(problems)


def test_exercise_solutions_are_hidden_until_clicked(walk):
    """Every sphinx-exercise solution starts folded and opens with its toggle button."""
    pages = {name: rec["solutions"] for name, rec in walk.items() if rec.get("solutions")}
    assert pages, "no chapter uses sphinx-exercise solutions"
    for name, s in pages.items():
        assert s["exercises"] >= s["solutions"] > 0, (name, s)
        assert s["shown"] == [], f"{name}: solutions {s['shown']} are shown before a click"
        assert s["opens"], f"{name}: the first solution does not open with its button"
