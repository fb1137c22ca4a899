"""A live character for the browser: a steering policy on A-MDM as one ONNX graph, and its data.

:func:`live_bundle` writes what ``static/live.js`` needs to run a character in the reader's
browser with ONNX Runtime Web: the policy + A-MDM frame graph of :mod:`minimdm.fast` (fp32: the
8-bit weights run slower in WebAssembly) and a JSON file with its metadata, the skeleton's
parents and names, and start frames (normalized) from the base model's training takes.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch

from minimdm.fast import export_onnx, frame_graph
from minimdm.fast.onnx import metadata
from minimdm.files import atomic_write

__all__ = ["live_bundle"]


def live_bundle(
    out: str | os.PathLike, policy: str = "rl_joystick", n_starts: int = 8, seed: int = 0
) -> dict[str, Path]:
    """Write ``<stem>.onnx`` and ``<stem>.json`` for ``static/live.js`` into folder ``out``.

    Args:
        out: the folder (made if missing).
        policy: a joystick policy checkpoint (a shipped name or a path).
        n_starts: start frames drawn from the base model's training takes.
        seed: seeds that draw.

    Returns:
        ``{"model": path, "data": path}``.
    """
    from minimdm.rl.train import corpus_starts

    graph = frame_graph(policy)
    if graph.kind != "policy" or graph.steering.task.name != "joystick":
        raise ValueError(f"{policy} must be a joystick steering policy, got kind {graph.kind!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stem = Path(str(policy)).name
    model = out / f"{stem}.onnx"
    export_onnx(graph, model, batch=1)  # one character: level-only parts fold into constants
    base = graph.steering.checkpoint.metadata["base"]["name"]
    from minimdm.fast.graphs import load

    frames = corpus_starts(load(base), "train")  # (P, D) feature units
    g = torch.Generator().manual_seed(seed)
    pick = torch.randperm(len(frames), generator=g)[:n_starts]
    starts = graph.steering.cm.normalize(frames[pick])  # (n, D)
    meta = metadata(graph, batch=1)
    data = {
        "model": model.name,
        "metadata": meta,
        "starts": [[round(float(v), 6) for v in row] for row in starts],
    }
    path = out / f"{stem}.json"
    atomic_write(path, json.dumps(data))
    return {"model": model, "data": path}
