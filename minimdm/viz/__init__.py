"""Skeleton animation: animated 3D stick figures that show in a live kernel and a static book.

Every function takes *motions* of global joint positions, shape ``(F, J, 3)`` in metres, in
the z-up world used everywhere in minimdm (the ground is the plane ``z = 0``), as numpy arrays
or torch tensors, and the skeleton's *parents* (``-1`` for the root): a
:class:`minimdm.motion.skeleton.Skeleton`, anything with a ``.parents`` attribute (its ``.names``,
if
any, let us draw a head), or a plain list of parent indices. The root's (the first joint with
parent ``-1``) ground projection is the trail, and the camera follows it.

* :func:`animate` renders one or several motions to a GIF or MP4 and returns an
  :class:`Animation`, which Jupyter shows inline as a base64 ``<img>`` (GIF) or ``<video>``
  (MP4), so the published book shows it without a kernel.
* :func:`render_frame` renders one still pose to an image array; :func:`filmstrip` puts a row of
  still frames in a matplotlib figure (the static figure beside a widget).
* :func:`scrubber` is an ipywidgets frame scrubber (Play + slider) for live kernels.
* :func:`plot_trajectories` draws top-down root paths of several runs, with optional targets;
  :func:`book_style` sets matplotlib up for figures that the book's column shows at their size.
* :func:`player` is a 3D player (three.js) as one HTML output: turn, zoom, play, scrub and
  compare characters, in a live kernel and in the static book alike, offline; its payload
  (:mod:`~minimdm.viz.payload`) stores positions as gzipped int16 codes.

Rendering uses pyvista off-screen (EGL, no display needed): one bone ``PolyData`` per character
feeds a tube filter and a sphere glyph, and only its points change from frame to frame. If
pyvista or EGL fails, we warn once and fall back to a matplotlib renderer (``backend=
"matplotlib"`` picks it by choice).

Colours tell real from generated motion: :data:`REAL` (steel blue) for data, :data:`GENERATED`
(orange) for samples, and :data:`PALETTE` for several samples (its first two entries are
``REAL`` and ``GENERATED``); :data:`TARGET` (red) draws goals and keyframes. Any matplotlib
colour, or the words ``"real"``, ``"generated"`` and ``"target"``, can be passed as a colour.

The package splits by concern: :mod:`~minimdm.viz.scene` (input checks, colours, camera and
trails), :mod:`~minimdm.viz.render` (the pyvista and matplotlib renderers),
:mod:`~minimdm.viz.animation` (:func:`animate`, :func:`render_frame`, GIF/MP4 files),
:mod:`~minimdm.viz.plots` (:func:`filmstrip`, :func:`scrubber`, :func:`plot_trajectories`),
:mod:`~minimdm.viz.payload` (the player's checked, compact payload) and
:mod:`~minimdm.viz.webplayer` (:func:`player`; its JavaScript is in ``static/``).
"""

# The private helpers ``_build_scene`` and ``_render`` are re-exported for tests and benchmarks.
# Module state (``_PYVISTA_ERROR``) and ``_PyvistaRenderer`` live in :mod:`.render`: read or
# patch them there (``viz.render._PYVISTA_ERROR``); a copy here would not follow them.
from .animation import Animation, animate, render_frame
from .plots import COLUMN_INCHES, book_style, filmstrip, plot_trajectories, scrubber
from .render import _render as _render
from .scene import GENERATED, PALETTE, REAL, TARGET
from .scene import _build_scene as _build_scene
from .webplayer import Player, player

__all__ = [
    "REAL",
    "GENERATED",
    "TARGET",
    "PALETTE",
    "Animation",
    "animate",
    "render_frame",
    "COLUMN_INCHES",
    "book_style",
    "filmstrip",
    "scrubber",
    "plot_trajectories",
    "Player",
    "player",
]
