"""The fast path: one frame (or CAMDM planning call), every denoising step, as one ONNX graph.

The eager samplers run the library's one reverse chain (:mod:`minimdm.diffusion`) step by step
in Python; at batch 1 on a CPU, per-operation overhead sets their speed. The fast path does not
write a second sampler. It traces the model's own per-frame step, with its noise as an input
(:class:`~minimdm.diffusion.NoiseTape`), into one graph, and runs that graph in ONNX Runtime:

* :mod:`~minimdm.fast.graphs`: :class:`FrameGraph`, the per-frame step of each checkpoint kind
  (:data:`FRAME_GRAPHS`: ``amdm`` with DDPM or DDIM, ``aamdm_motion``, ``policy`` on A-MDM,
  and ``camdm``: :class:`CAMDMPlan`, a whole planning call, 8 steps with classifier-free
  guidance, the CFG scale an input);
* :mod:`~minimdm.fast.onnx`: :func:`export_onnx` (the graph, its weights and its metadata in
  one file, ``minimdm export --onnx``), :func:`read_metadata`, and :class:`FastFrame`, the
  drop-in for the eager step: pass it as ``fast=`` to
  :func:`minimdm.amdm.sampling.rollout` or :func:`minimdm.aamdm.eval.rollout_aamdm`, or (CAMDM)
  as ``planner=`` to :class:`minimdm.camdm.controller.CAMDMController`.

    fast = fast_frame("amdm")                       # the shipped book model
    x1 = fast(x0, torch.Generator().manual_seed(0))  # the eager Sampler.frame's x1, within 1e-4

    plan = fast_frame("camdm")                      # one planning call: (B, P, D) -> (B, F, D)
    ctl = CAMDMController("checkpoints/camdm", planner=plan)  # the eager controller's frames
    ctl = CAMDMController("checkpoints/camdm", planner=fast_planner("camdm"))
    # the same, with the plans at gamma = 1 (all but the second after a style change) on a
    # graph of the conditional model alone: half the arithmetic

``benchmarks/realtime.py`` measures eager against fast.
"""

from .graphs import (
    FRAME_GRAPHS,
    AAMDMFrame,
    AMDMFrame,
    CAMDMPlan,
    FrameGraph,
    Port,
    SteeredFrame,
    frame_graph,
)
from .onnx import (
    FORMAT,
    METADATA_KEY,
    CAMDMPlanner,
    FastFrame,
    export_onnx,
    fast_frame,
    fast_planner,
    read_metadata,
)

__all__ = [
    "Port",
    "FrameGraph",
    "AMDMFrame",
    "AAMDMFrame",
    "SteeredFrame",
    "CAMDMPlan",
    "FRAME_GRAPHS",
    "frame_graph",
    "FORMAT",
    "METADATA_KEY",
    "export_onnx",
    "read_metadata",
    "FastFrame",
    "fast_frame",
    "CAMDMPlanner",
    "fast_planner",
]
