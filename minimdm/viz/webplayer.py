"""The 3D skeleton player: one HTML output that a live kernel and the static book both show.

:func:`player` checks its input and builds a payload (:mod:`~minimdm.viz.payload`), then returns
a :class:`Player`, an ``IPython.display.HTML`` whose output holds

* a small poster (a PNG of the middle frame, rendered like every other minimdm figure) that
  readers without JavaScript or WebGL see;
* the payload as JSON;
* a boot script that mounts ``static/player.js`` (three.js) on the poster's place.

The first player shown in a kernel also carries the code: ``three.module.min.js`` and
``player.js``, gzipped and base64-encoded (about 240 kB). The page decompresses them with
``DecompressionStream`` and imports them from ``blob:`` URLs, so nothing comes from the network,
and later players on the page only wait for that module. A re-run of the cell that carried the
code carries it again (its old output, and the code in it, is about to be replaced), and a player
whose page lacks the code finds the copy the first one left in the browser's ``localStorage``;
failing that, it says so and keeps its poster. ``embed=True`` always carries the code, and
:meth:`Player.save` writes a page that stands alone.
"""

from __future__ import annotations

import base64
import hashlib
import html
import io
import json
import os
from collections.abc import Sequence
from functools import cache
from pathlib import Path
from typing import Any, Literal

import numpy as np
from IPython.display import HTML

from ..files import atomic_write
from ..validate import InputError
from .payload import build_payload, decode_positions
from .scene import _check_size

__all__ = ["Player", "player"]

STATIC = Path(__file__).with_name("static")
"""The player's JavaScript: ``player.js`` and the vendored ``three.module.min.js``."""
POSTER_WIDTH = 320  # pixels; the poster is a placeholder, kept small (about 10-25 kB)


# --------------------------------------------------------------------------- the code, once


@cache
def _library() -> tuple[str, dict[str, str]]:
    """(key, {"three", "player"}): the two modules gzipped and base64-encoded; the key names
    this version of them, so that players of two minimdm versions on one page do not mix."""
    from .payload import _b64gz

    src = {name: (STATIC / f"{name}.js").read_bytes() for name in ("three.module.min", "player")}
    key = "minimdm-player-" + hashlib.sha1(src["three.module.min"] + src["player"]).hexdigest()[:12]
    return key, {"three": _b64gz(src["three.module.min"]), "player": _b64gz(src["player"])}


_KERNEL: dict[str, Any] = {"embedded": False, "cell": None, "count": None}


def _where() -> tuple[str | None, int | None]:
    """(cell id, execution count) of the running IPython cell, or (None, None) outside IPython.

    The cell id is the front end's (JupyterLab sends one with every execution request)."""
    try:
        from IPython import get_ipython
    except ImportError:  # pragma: no cover - IPython is a dependency of ipywidgets
        return None, None
    ip = get_ipython()
    if ip is None:
        return None, None
    result = getattr(getattr(ip, "displayhook", None), "exec_result", None)
    cell = getattr(getattr(result, "info", None), "cell_id", None)
    return cell, getattr(ip, "execution_count", None)


def _take_embed() -> bool:
    """Whether the player being shown now carries the code (see the module docstring)."""
    cell, count = _where()
    rerun = cell is not None and cell == _KERNEL["cell"] and count != _KERNEL["count"]
    if not _KERNEL["embedded"] or rerun:
        _KERNEL.update(embedded=True, cell=cell, count=count)
        return True
    return False


STILL_NOTE = (
    "A still of the middle frame. Run this cell (in a trusted notebook) to play it in 3D: "
    "drag to turn, scrub the frames."
)
"""What a stored player says where its script does not run (an untrusted notebook, a viewer
without JavaScript); the script hides it."""

_BOOT = """(function () {
  var KEY = %(key)s, ID = %(id)s, LIB = %(lib)s;
  var reg = window.__minimdmPlayer = window.__minimdmPlayer || {};
  var box = document.getElementById(ID);
  box.querySelector(".mmp-msg").style.display = "none";  // the script runs: no still note
  function say(m) {
    var e = box.querySelector(".mmp-msg"); e.textContent = m; e.style.display = "";
  }
  if (!window.DecompressionStream || !window.WebGLRenderingContext) {
    say("This browser cannot run the 3D player; the picture above is its middle frame."); return;
  }
  function text(b64) {
    var bin = atob(b64), bytes = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    var s = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
    return new Response(s).text();
  }
  function url(code) { return URL.createObjectURL(new Blob([code], {type: "text/javascript"})); }
  function load(lib) {
    return Promise.all([text(lib.three), text(lib.player)]).then(function (src) {
      return import(url(src[1].replace('from "three"', 'from "' + url(src[0]) + '"')));
    });
  }
  if (LIB && !reg[KEY]) {
    reg[KEY] = load(LIB);
    try { localStorage.setItem(KEY, JSON.stringify(LIB)); } catch (e) {}
  }
  function find(t0) {
    if (reg[KEY]) return Promise.resolve(reg[KEY]);
    if (document.readyState === "complete" && Date.now() - t0 > 1500) {
      var s = null;
      try { s = localStorage.getItem(KEY); } catch (e) {}
      if (s) { reg[KEY] = load(JSON.parse(s)); return reg[KEY]; }
      return Promise.resolve(null);
    }
    return new Promise(function (r) { setTimeout(r, 50); }).then(function () { return find(t0); });
  }
  find(Date.now()).then(function (mod) {
    if (!mod) {
      say("The 3D player's code is not on this page: run the notebook's first player cell " +
          "again, or pass embed=True. The picture above is the middle frame.");
      return;
    }
    var data = JSON.parse(box.querySelector("script.mmp-data").textContent);
    return mod.mount(box, data).then(function () {
      var p = box.querySelector(".mmp-poster"); if (p) p.remove();
    });
  }).catch(function (e) { say("3D player: " + e.message); });
})();"""


# --------------------------------------------------------------------------- poster


def _poster(payload: dict[str, Any], parents: list[int], names: Any) -> str | None:
    """A small PNG (base64) of the middle frame, characters in their lanes, targets in red."""
    from PIL import Image

    from .animation import render_frame

    J = len(parents)
    ms = [decode_positions(m, J) + np.asarray(m["offset"]) for m in payload["motions"]]
    f = max(len(m) for m in ms) // 2
    poses = [m[min(f, len(m) - 1)] for m in ms]
    offsets = [np.asarray(m["offset"]) for m in payload["motions"]]
    targets = []
    for s in payload["shapes"]:
        lanes = [s["motion"]] if s["motion"] >= 0 else range(len(ms))
        for i in lanes if payload["layout"] == "side" else [s["motion"]]:
            off = offsets[i] if i >= 0 else 0.0
            if s["kind"] in ("target", "path"):
                targets.append(np.asarray(s["points"]) + off)
            else:
                targets.append(np.asarray(s["poses"]).reshape(-1, J, 3) + off)
    w, h = payload["width"], payload["height"]
    size = (POSTER_WIDTH, max(16, round(POSTER_WIDTH * h / w)))
    skel = type("Parents", (), {"parents": parents, "names": names})()
    img = render_frame(
        poses,
        skel,
        colors=[m["color"] for m in payload["motions"]],
        labels=[m["label"] for m in payload["motions"]],
        targets=targets or None,
        size=size,
        view=tuple(payload["view"]),
    )
    buf = io.BytesIO()
    Image.fromarray(img).quantize(colors=48, method=Image.Quantize.MEDIANCUT).save(
        buf, format="PNG", optimize=True
    )
    return base64.b64encode(buf.getvalue()).decode("ascii")


# --------------------------------------------------------------------------- the output


class Player(HTML):
    """An HTML output with a 3D skeleton player (see :func:`player`).

    ``data`` is the page fragment that stands alone (it carries the code); what Jupyter shows
    carries the code only for the first player of the kernel (see the module docstring).
    """

    def __init__(self, payload: dict[str, Any], poster: str | None, embed: bool | None) -> None:
        self.payload = payload
        self.poster = poster
        self.embed = embed
        self._shown = 0
        super().__init__(data=self.html(embed=True))

    @property
    def n_frames(self) -> int:
        return max(m["n"] for m in self.payload["motions"])

    def html(self, embed: bool, uid: str | None = None) -> str:
        """The HTML fragment; ``embed`` carries the code (``player.js`` and three.js)."""
        text = json.dumps(self.payload, separators=(",", ":"))
        digest = hashlib.sha1(text.encode()).hexdigest()[:10]
        uid = uid or f"mmp-{digest}-{self._shown}"
        key, lib = _library()
        boot = _BOOT % {
            "key": json.dumps(key),
            "id": json.dumps(uid),
            "lib": json.dumps(lib) if embed else "null",
        }
        w, h = self.payload["width"], self.payload["height"]
        labels = ", ".join(m["label"] for m in self.payload["motions"] if m["label"])
        alt = f"3D skeleton player: {len(self.payload['motions'])} motion(s)" + (
            f" ({labels})" if labels else ""
        )
        if self.poster:
            still = (
                f'<img class="mmp-poster" alt="{html.escape(alt)}" width="{w}" '
                f'style="display:block;width:100%;height:auto;border-radius:4px" '
                f'src="data:image/png;base64,{self.poster}">'
            )
        else:
            still = (
                f'<div class="mmp-poster" style="aspect-ratio:{w}/{h};background:#f3f4f6;'
                f'border-radius:4px"></div>'
            )
        safe = text.replace("</", "<\\/")  # a label may not close the script element
        return (
            f'<div class="minimdm-player" id="{uid}" style="width:{w}px;max-width:100%">'
            f"{still}"
            '<div class="mmp-msg" style="font:12px system-ui,sans-serif;color:#555">'
            f"{STILL_NOTE}</div>"
            f'<script type="application/json" class="mmp-data">{safe}</script>'
            f"</div>\n<script>{boot}</script>"
        )

    def _repr_html_(self) -> str:
        self._shown += 1
        embed = self.embed if self.embed is not None else _take_embed()
        return self.html(embed=embed)

    def save(self, path: str | os.PathLike) -> Path:
        """Write a page (.html) with this player that works on its own, offline."""
        path = Path(path)
        if path.suffix.lower() not in (".html", ".htm"):
            raise InputError(f"path must end in .html, got {str(path)!r}")
        body = self.html(embed=True)
        atomic_write(
            path,
            '<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>minimdm player</title>'
            f"</head><body>\n{body}\n</body></html>\n",
        )
        return path

    def __repr__(self) -> str:
        n, fps = len(self.payload["motions"]), self.payload["fps"]
        return f"<minimdm Player: {n} motion(s), {self.n_frames} frames @ {fps:g} fps>"


def _check_player_options(
    poster: bool, embed: bool | None, size: tuple[int, int]
) -> tuple[int, int]:
    """Check the arguments :func:`player` keeps for itself; the size as ``(width, height)``."""
    if embed is not None and not isinstance(embed, bool):
        raise InputError(f"embed must be None, True or False, got {embed!r}")
    if not isinstance(poster, bool):
        raise InputError(f"poster must be True or False, got {poster!r}")
    return _check_size(size)


def _make_player(
    payload: dict[str, Any], size: tuple[int, int], poster: bool, embed: bool | None
) -> Player:
    """The :class:`Player` of a payload, at ``size`` (width, height), with its poster if asked."""
    payload["width"], payload["height"] = size
    still = _poster(payload, payload["parents"], payload["names"]) if poster else None
    return Player(payload, still, embed)


def player(
    motions: Any,
    skeleton: Any,
    fps: float = 30.0,
    *,
    labels: Sequence[str] | None = None,
    colors: Any = None,
    layout: Literal["side", "overlay"] = "side",
    targets: Any = None,
    paths: Any = None,
    keyframes: Any = None,
    feet: Sequence[str | int] | bool | None = None,
    contacts: Any = None,
    follow: bool = True,
    view: tuple[float, float] | None = None,
    size: tuple[int, int] = (640, 360),
    poster: bool = True,
    autoplay: bool = True,
    embed: bool | None = None,
) -> Player:
    """A 3D skeleton player (three.js) as an HTML output, the same in JupyterLab and the book.

    Readers turn the view (drag), pan (right-drag), zoom (click, then scroll), play and pause,
    scrub frames and pick a speed; the page needs no network and no kernel. Display the returned
    :class:`Player` or leave it last in a cell; ``.save("x.html")`` writes a page on its own.

    Args:
        motions: global joint positions ``(T, J, 3)`` in metres, z-up (numpy or torch), a
            batch ``(B, T, J, 3)``, a list of them (lengths may differ: shorter ones hold their
            last frame), a :class:`~minimdm.motion.data.Clip`, or ``(root_pos (T, 3), local_rot
            (T, J, 4) quaternions or (T, J, 3, 3))``, which forward kinematics turns into
            positions (``skeleton`` must then be a :class:`~minimdm.motion.skeleton.Skeleton`).
        skeleton: a Skeleton, anything with ``.parents`` (and ``.names``: a leaf called head or
            neck gets a head), or a list of parent indices, ``-1`` for a root, each parent
            before its child.
        fps: the motions' frame rate (playback runs in real time at speed 1×).
        labels: one label per motion, drawn above its character in its colour.
        colors: one colour per motion or one for all; default :data:`~minimdm.viz.PALETTE`.
        layout: ``"side"``: each character in its own lane, side by side, across the direction
            they travel; ``"overlay"``: all in place, one on the other.
        targets: points ``(K, 2)`` on the ground or ``(K, 3)``, drawn as red spheres over rings;
            one array for every character (in every lane), or a list with one per motion.
        paths: polylines ``(K, 2|3)`` to follow, dashed red; for all or one per motion.
        keyframes: ghost poses ``(K, J, 3)``, or ``{"frames": [...], "poses": ...}`` /
            ``(frames, poses)`` so that each lights up at its frame; for all or one per motion.
        feet: the foot joints (names or indices) whose contacts are shown as discs on the
            ground; default the skeleton's ``foot_joints``; ``False`` shows none.
        contacts: a list of one ``(T, n_feet)`` bool array per motion; default: detected (a foot
            within 2.5 cm of its resting height and slower than 0.6 m/s).
        follow: the camera follows the characters (their root, smoothed over ±1 s) and frames
            their bodies as they are, drawing back as far as characters that part need; False:
            one view of every frame and all of the path. The box under the player switches.
        view: camera (azimuth, elevation) in degrees, z-up world, as in
            :func:`~minimdm.viz.animate`; default: across the lanes.
        size: (width, height) in pixels; the player shrinks with a narrower page.
        poster: render a small PNG of the middle frame for readers without JavaScript/WebGL.
        autoplay: start playing as soon as it shows.
        embed: carry the player's code (about 240 kB) in this output: None decides by itself
            (once per kernel), True always, False never.

    Raises:
        InputError: a ``ValueError`` naming the bad input, before any HTML is made.
    """
    size = _check_player_options(poster, embed, size)
    payload = build_payload(
        motions,
        skeleton,
        fps=fps,
        labels=labels,
        colors=colors,
        layout=layout,
        targets=targets,
        paths=paths,
        keyframes=keyframes,
        feet=feet,
        contacts=contacts,
        follow=follow,
        view=view,
        autoplay=autoplay,
    )
    return _make_player(payload, size, poster, embed)
