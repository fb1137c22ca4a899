"""Shared test set-up: off-screen rendering without a display, a non-interactive matplotlib, and
the ``one_thread`` fixture."""

import os

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
