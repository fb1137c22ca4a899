"""Shared test set-up: off-screen rendering without a display, a non-interactive matplotlib, the
``one_thread`` fixture, and ``browser``: Debian's Chromium driven by Playwright, for the tests
that open pages (the book, the 3D player, the live character)."""

import os
import shutil
from pathlib import Path

import pytest

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture
def one_thread():
    """Run the test on one torch thread, then restore the count.

    Tiny networks run fastest on one thread, and one thread does not fight other processes for
    the cores. A module opts in with ``pytestmark = pytest.mark.usefixtures("one_thread")``.
    """
    from minimdm.utils import num_threads  # imported late: the variables above come first

    with num_threads(1):
        yield


# -------------------------------------------------------------------------- a real browser

CHROMIUM = ("/usr/bin/chromium", "/usr/bin/chromium-browser")
ARGS = [
    "--no-sandbox",  # CI runs as root
    "--use-angle=swiftshader",  # WebGL on the CPU: no GPU, no display
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",  # and no network of its own
    "--disable-component-update",
    "--disable-sync",
    "--disable-default-apps",
    "--disable-extensions",
    "--no-first-run",
]


def _unavailable(why: str) -> None:
    msg = (
        f"{why}: install Chromium with `apt-get install -y chromium` (and `pip install playwright`)"
    )
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"CI must run the browser test, but {msg}")
    pytest.skip(msg)


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium (Playwright, never its own browser download), offline; skipped with an
    install hint where there is none, except in CI (``CI=true``), where that fails the test."""
    exe = next((p for p in CHROMIUM if Path(p).exists()), shutil.which("chromium"))
    if exe is None:
        _unavailable("no Chromium found")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _unavailable("Playwright is not installed")
    with sync_playwright() as pw:
        # launch() starts from a fresh, temporary profile each time
        b = pw.chromium.launch(executable_path=exe, headless=True, args=ARGS)
        yield b
        b.close()
