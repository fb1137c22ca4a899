"""Skeleton rendering speed: 150 frames of one character to a GIF (issue 3: under 20 s on a CPU).

Renders the DeepMimic walk, unrolled to ``--frames`` frames at 30 Hz, with
:func:`minimdm.viz.animate` (every frame, ``stride=1``) for each backend, and prints one JSON
line per backend and run (after all runs):

    bench, backend, run (cold: first call in the process, with the pyvista/EGL start-up;
    warm: the same call again), config, hardware, seconds, ms_per_frame, gif_bytes

Not a test. Examples:

    python benchmarks/render.py                         # pyvista and matplotlib, 320 x 240
    python benchmarks/render.py --backends pyvista --size 480 360 --format mp4
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")  # before vtk loads


from common import hardware  # noqa: E402

from minimdm import viz  # noqa: E402
from minimdm.motion.data import load_clips  # noqa: E402


def render_hardware() -> dict:
    """:func:`common.hardware` plus the platform and the rendering stack."""
    info = {**hardware(), "platform": platform.platform(), "python": platform.python_version()}
    try:
        import matplotlib

        info["matplotlib"] = matplotlib.__version__
        import pyvista as pv
        import vtk

        info["pyvista"] = pv.__version__
        info["vtk"] = vtk.vtkVersion.GetVTKVersion()
        info["gl_renderer"] = pv.GPUInfo().renderer  # e.g. llvmpipe: Mesa's CPU rasteriser
    except Exception as e:  # no pyvista or no EGL: the matplotlib numbers still count
        info["pyvista_error"] = f"{type(e).__name__}: {e}"
    return info


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=150, help="frames rendered (30 Hz motion)")
    p.add_argument(
        "--clip", default="walk", help="a looping clip of minimdm.motion.data.CLIP_NAMES"
    )
    p.add_argument("--size", type=int, nargs=2, default=[320, 240], metavar=("W", "H"))
    p.add_argument("--fps", type=float, default=30.0, help="playback rate written to the file")
    p.add_argument("--format", default="gif", choices=["gif", "mp4"])
    p.add_argument("--backends", nargs="+", default=["pyvista", "matplotlib"])
    p.add_argument("--repeat", type=int, default=2, help="runs per backend (first one is cold)")
    args = p.parse_args()

    clip = load_clips(loop_frames=args.frames, names=[args.clip])[args.clip]
    motion = clip.positions[: args.frames]  # (F, J, 3)
    config = {
        "clip": args.clip,
        "frames": len(motion),
        "joints": motion.shape[1],
        "size": list(args.size),
        "fps": args.fps,
        "stride": 1,
        "format": args.format,
        "trail": True,
        "follow": True,
    }
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for backend in args.backends:
            for run in range(args.repeat):
                out = Path(tmp) / f"{backend}_{run}.{args.format}"
                t0 = time.perf_counter()
                anim = viz.animate(
                    motion,
                    clip.skeleton,
                    labels=[args.clip],
                    colors="real",
                    size=tuple(args.size),
                    fps=args.fps,
                    stride=1,
                    out=out,
                    backend=backend,
                )
                seconds = time.perf_counter() - t0
                row = {
                    "bench": "render",
                    "backend": backend,
                    "run": "cold" if run == 0 else "warm",
                    "config": config,
                    "fell_back_to_matplotlib": backend == "pyvista"
                    and viz.render._PYVISTA_ERROR is not None,
                    "seconds": round(seconds, 2),
                    "ms_per_frame": round(1000 * seconds / anim.n_frames, 1),
                    f"{args.format}_bytes": out.stat().st_size,
                }
                rows.append(row)
    hw = render_hardware()  # after the runs: probing the GPU would warm up pyvista for the cold run
    for row in rows:
        print(json.dumps({**row, "hardware": hw}), flush=True)


if __name__ == "__main__":
    main()
