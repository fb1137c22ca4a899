"""The fast path: one frame, every denoising step, as one ONNX graph (issue 16).

The eager samplers run the library's one reverse chain (:mod:`minimdm.diffusion`) step by step
in Python; at batch 1 on a CPU, per-operation overhead sets their speed. The fast path does not
write a second sampler. It traces the model's own per-frame step, with its noise as an input
(:class:`~minimdm.diffusion.NoiseTape`), into one graph, and runs that graph in ONNX Runtime:

* :mod:`~minimdm.fast.graphs`: :class:`FrameGraph`, the per-frame step of each checkpoint kind
  (:data:`FRAME_GRAPHS`: ``amdm`` with DDPM or DDIM, ``aamdm_motion``, ``policy`` on A-MDM);
* :mod:`~minimdm.fast.onnx`: :func:`export_onnx` (the graph, its weights and its metadata in
  one file, ``minimdm export --onnx``), :func:`read_metadata`, and :class:`FastFrame`, the
  drop-in for the eager step: pass it as ``sampler=`` to
  :func:`minimdm.amdm.sampling.rollout` or :func:`minimdm.aamdm.eval.rollout_aamdm`.

    fast = fast_frame("amdm")                       # the shipped book model
    x1 = fast(x0, torch.Generator().manual_seed(0))  # the eager next_frame's x1, within 1e-4

``benchmarks/realtime.py`` measures eager against fast.
"""

from .graphs import FRAME_GRAPHS, AAMDMFrame, AMDMFrame, FrameGraph, SteeredFrame, frame_graph
from .onnx import FORMAT, METADATA_KEY, FastFrame, export_onnx, fast_frame, read_metadata

__all__ = [
    "FrameGraph",
    "AMDMFrame",
    "AAMDMFrame",
    "SteeredFrame",
    "FRAME_GRAPHS",
    "frame_graph",
    "FORMAT",
    "METADATA_KEY",
    "export_onnx",
    "read_metadata",
    "FastFrame",
    "fast_frame",
]
