"""Real time on a CPU: the eager per-frame step against the fast path, in one run (issue 16).

For each model, batch (1 and 64) and thread count (one and all), it times one frame, every
denoising step, three ways on the same inputs:

* ``eager``: the library's own step in PyTorch (:class:`minimdm.fast.FrameGraph.frame`, i.e.
  ``Sampler.frame`` / ``aamdm_frame`` / the policy and its steerer);
* ``fast``: the same step traced into one ONNX graph, run by ONNX Runtime
  (:class:`minimdm.fast.FastFrame`), its noise drawn from the same generator; it matches eager
  within 1e-4 (``max_abs_diff``);
* ``fast_int8``: that graph with 8-bit block weights (``weights="int8"``), an approximation
  (``int8_rel_rms``: its frame's RMS difference from fp32's over the frame's RMS).

Models: the book's A-MDM (6 x 384, T = 20, DDPM, and DDIM over 5 steps), AAMDM (3 GAN + 2
polishing steps, then the decoder), the joystick policy steering A-MDM, a paper-size A-MDM
(10 x 1024, T = 40) with random weights (speed does not depend on the weights' values), and
CAMDM, whose unit is not a frame but a planning call (:class:`minimdm.fast.CAMDMPlan`: F = 45
future frames, 8 denoising steps with classifier-free guidance at gamma = 0.7, both model calls
in one forward pass of 2 B rows; the controller applies M = 15 planned frames per call, so a
character runs at ``M / plan time`` frames per second when planning dominates), and
``camdm_gamma1``, the plan at gamma = 1 (the conditional model alone, ``guide="none"``: the
graph that :class:`minimdm.fast.CAMDMPlanner` runs for every plan but those in the second after
a style change), and ``camdm_each``, the graph of the book's controller (``guide="each"``: every
plan guided, on the style at steady state and on the past after a change, 2 B rows). It also
records the engine choice at batch 1 on one thread (TorchScript, ONNX Runtime, and with
``--compile`` torch.compile), the load of the machine (``uptime``), the memory bandwidth and
the goals with the arithmetic that bounds them. Times are medians of ``--repeats`` blocks, the
engines interleaved, as the machine is shared.

    python benchmarks/realtime.py                # ~8 min on the 2-core build machine
    python benchmarks/realtime.py --quick        # A-MDM, and CAMDM at batch 1 only; 3 repeats
    python benchmarks/realtime.py --models camdm # some models only

Prints JSON lines and appends them to ``benchmarks/results/realtime.jsonl``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
import warnings

import numpy as np
import torch
from common import ROOT, emit, hardware

from minimdm.amdm.models import DenoiserConfig, MLPDenoiser
from minimdm.amdm.sampling import Sampler
from minimdm.diffusion import NoiseSchedule, StepSettings
from minimdm.fast import AMDMFrame, CAMDMPlan, FastFrame, export_onnx, frame_graph
from minimdm.utils import num_threads

RESULTS = ROOT / "benchmarks" / "results" / "realtime.jsonl"
GOALS_MS = {
    "amdm": 2.0,
    "paper_10x1024": 20.0,
    "camdm": 15.0,
    "camdm_gamma1": 15.0,
    "camdm_each": 15.0,
}
"""Issue 16's goals, ms per frame (CAMDM: per planning call) on one core at batch 1."""
CAMDM_M = 15
"""Frames the CAMDM controller applies per planning call (ControlConfig.M)."""
CAMDM_GAMMA = 0.7
"""The CFG scale timed: not 1, so that eager runs both halves of eq. 5 as the graph does."""
MODELS = (
    "amdm",
    "amdm_ddim5",
    "aamdm",
    "rl_joystick",
    "paper_10x1024",
    "camdm",
    "camdm_gamma1",
    "camdm_each",
)
QUICK = ("amdm", "amdm_ddim5", "camdm", "camdm_gamma1", "camdm_each")


def load() -> dict:
    """The machine's load average and uptime line (the machine is shared)."""
    one, five, fifteen = os.getloadavg()
    return {"loadavg": [round(one, 2), round(five, 2), round(fifteen, 2)]}


def cpu_flags() -> dict:
    """The CPU model and its AVX-512 flags (bf16, vnni), from /proc/cpuinfo."""
    try:
        text = open("/proc/cpuinfo").read()
    except OSError:
        return {}
    model = next((ln.split(":", 1)[1].strip() for ln in text.splitlines()
                  if ln.startswith("model name")), None)  # fmt: skip
    flags = next((ln.split(":", 1)[1].split() for ln in text.splitlines()
                  if ln.startswith("flags")), [])  # fmt: skip
    return {"cpu_model": model, "avx512": sorted(f for f in flags if f.startswith("avx512"))}


def bandwidth(mb: int, seconds: float = 0.3) -> float:
    """GB/s of one thread summing a float32 array of ``mb`` MB again and again."""
    a = np.ones(mb * 2**18, dtype=np.float32)
    a.sum()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a.sum()
        n += 1
    return round(n * a.nbytes / (time.perf_counter() - t0) / 1e9, 1)


def interleaved(fns: dict, repeats: int, block_s: float = 0.1) -> dict[str, float]:
    """Median ms per call of each function, timed in blocks taken in turn."""
    calls = {}
    for name, fn in fns.items():
        fn()  # warm-up
        t0 = time.perf_counter()
        fn()
        calls[name] = max(1, int(block_s / max(time.perf_counter() - t0, 1e-6)))
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            for _ in range(calls[name]):
                fn()
            times[name].append((time.perf_counter() - t0) / calls[name] * 1e3)
    return {k: round(statistics.median(v), 3) for k, v in times.items()}


def paper_graph() -> AMDMFrame:
    """The paper's denoiser size (A-MDM §7: 10 layers of 1024, T = 40), random weights."""
    torch.manual_seed(0)
    D = 255  # the book's frame size
    net = MLPDenoiser(DenoiserConfig(D, D, 1024, 10, 128, "eps")).eval()
    settings = StepSettings(predicts="eps", clip_x0=3.0)
    return AMDMFrame(Sampler(net, schedule=NoiseSchedule("cosine", 40), settings=settings))


def inputs(graph, batch: int):
    g = torch.Generator().manual_seed(0)
    if isinstance(graph, CAMDMPlan):  # past near the data's mean, a style, a trajectory, gamma
        c = graph.controller
        L = c.layout
        mean = c.window_norm.mean.view(-1, L.dim)[: L.past]
        past = mean + 0.1 * torch.randn(batch, L.past, L.dim, generator=g)
        extra = {"style": torch.randint(len(L.styles), (batch,), generator=g),
                 "trajectory": torch.randn(batch, L.future, 4, generator=g)}  # fmt: skip
        if graph.guide != "none":
            extra["gamma"] = torch.full((batch,), CAMDM_GAMMA)
        if graph.guide == "each":  # half the characters guided on their style
            extra["on_style"] = torch.arange(batch) % 2
        return past, extra
    state = 0.5 * torch.randn(batch, graph.state_dim, generator=g)
    extra = {n: torch.randn(batch, w, generator=g) for n, w, _ in graph.extra_inputs}
    return state, extra


def plan_flops(graph) -> int:
    """FLOPs of one CAMDM planning call at batch 1 (matrix products, attention included), counted
    on the eager call with the fused encoder kernel off (the counter sees plain operations)."""
    from torch.utils.flop_counter import FlopCounterMode

    past, extra = inputs(graph, 1)
    fused = torch.backends.mha.get_fastpath_enabled()
    torch.backends.mha.set_fastpath_enabled(False)
    try:
        with torch.no_grad(), FlopCounterMode(display=False) as counter:
            graph.frame(past, torch.Generator().manual_seed(0), *extra.values())
    finally:
        torch.backends.mha.set_fastpath_enabled(fused)
    return counter.get_total_flops()


def frame_arithmetic(graph) -> dict:
    """A-MDM at batch 1: every denoising step reads every weight of the denoiser once."""
    if isinstance(graph, CAMDMPlan):  # every step: one call of the transformer on 2 B or B rows
        params = sum(p.numel() for p in graph.model.parameters())
        cfg = graph.guide != "none"
        return {"params": params, "network_calls_per_plan": graph.controller.schedule.T,
                "rows_per_call": "2 B (both halves of CFG)" if cfg else "B (conditional)",
                "gamma": CAMDM_GAMMA if cfg else 1.0,
                "GFLOP_per_plan_batch1": round(plan_flops(graph) / 1e9, 3)}  # fmt: skip
    cm = getattr(graph, "cm", None)
    if cm is None:
        return {}
    params = sum(p.numel() for p in cm.net.parameters())
    calls = len(graph.describe()["sampler"]["levels"])
    return {"params": params, "network_calls_per_frame": calls,
            "fp32_weight_MB_per_frame": round(4 * params * calls / 1e6, 1),
            "GFLOP_per_frame_batch1": round(2 * params * calls / 1e9, 3)}  # fmt: skip


def engines(graph, repeats: int, compile_too: bool) -> dict:
    """The engine choice: one frame at batch 1 on one thread, eager and three compiled forms."""
    state, extra = inputs(graph, 1)
    noise = graph.noise(1, torch.Generator().manual_seed(0))
    args = (state, *extra.values(), noise)
    out: dict = {}
    with num_threads(1), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ts = torch.jit.trace(graph, args, check_trace=False).eval()
        ts = torch.jit.optimize_for_inference(torch.jit.freeze(ts))
        fast = FastFrame(export_onnx(graph), threads=1)
        fns = {
            "eager": lambda: graph(*args),
            "torchscript": lambda: ts(*args),
            "onnxruntime": lambda: fast(state, noise=noise, **extra),
        }
        if compile_too:
            t0 = time.perf_counter()
            compiled = torch.compile(graph)
            compiled(*args)
            out["torch_compile_seconds"] = round(time.perf_counter() - t0, 1)
            fns["torch_compile"] = lambda: compiled(*args)
        out["ms_per_frame"] = interleaved(fns, repeats)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=7, help="timed blocks per engine (median)")
    p.add_argument("--quick", action="store_true",
                   help="A-MDM, and CAMDM at batch 1 only; 3 repeats")  # fmt: skip
    p.add_argument(
        "--models",
        nargs="+",
        choices=MODELS,
        default=None,
        help="the models to time (default: all; --quick: amdm amdm_ddim5 camdm)",
    )
    p.add_argument("--compile", action="store_true", help="also time torch.compile (slow)")
    p.add_argument("--out", default=str(RESULTS), help="append the JSON lines here")
    args = p.parse_args()
    repeats = 3 if args.quick else args.repeats
    out = None if args.quick else args.out
    all_threads = os.cpu_count() or 1
    run = {"bench": "realtime", "run": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    hw = {**hardware("cpu"), **cpu_flags()}
    import onnxruntime

    hw["onnxruntime"] = onnxruntime.__version__
    emit({**run, "record": "machine", "hardware": hw, "load_start": load(),
          "bandwidth_GBps_1thread": {"8MB": bandwidth(8), "24MB": bandwidth(24),
                                     "256MB": bandwidth(256)}}, out)  # fmt: skip

    print("building graphs ...", flush=True)
    build = {
        "amdm": lambda: frame_graph("amdm"),
        "amdm_ddim5": lambda: frame_graph("amdm", steps=5),
        "aamdm": lambda: frame_graph("aamdm"),
        "rl_joystick": lambda: frame_graph("rl_joystick"),
        "paper_10x1024": paper_graph,
        "camdm": lambda: frame_graph("camdm"),
        "camdm_gamma1": lambda: frame_graph("camdm", guide="none"),
        "camdm_each": lambda: frame_graph("camdm", guide="each"),
    }
    models = args.models or (QUICK if args.quick else MODELS)
    graphs = {k: build[k]() for k in MODELS if k in models}
    t0 = time.perf_counter()
    onnx = {k: (export_onnx(g), export_onnx(g, weights="int8")) for k, g in graphs.items()}
    emit({**run, "record": "export", "seconds": round(time.perf_counter() - t0, 1),
          "bytes": {k: [len(a), len(b)] for k, (a, b) in onnx.items()}}, out)  # fmt: skip

    if "amdm" in graphs:
        emit({**run, "record": "engines", "model": "amdm", "batch": 1, "threads": 1,
              **engines(graphs["amdm"], repeats, args.compile), "load": load()}, out)  # fmt: skip

    results = {}
    for name, graph in graphs.items():
        for threads in sorted({1, all_threads}):
            fp32 = FastFrame(onnx[name][0], threads=threads)
            int8 = FastFrame(onnx[name][1], threads=threads)
            for batch in (1,) if args.quick and name.startswith("camdm") else (1, 64):
                state, extra = inputs(graph, batch)
                gen = torch.Generator()
                # accuracy on the same noise: fp32 against eager, int8 against fp32
                with torch.no_grad(), num_threads(threads):
                    eager = graph.frame(state, gen.manual_seed(1), *extra.values())
                a = fp32(state, gen.manual_seed(1), **extra)
                b = int8(state, gen.manual_seed(1), **extra)
                diff = (a - eager).abs().max().item()
                rel = ((b - a).pow(2).mean().sqrt() / a.pow(2).mean().sqrt()).item()

                def eager_frame(graph=graph, state=state, extra=extra, gen=gen):
                    with torch.no_grad():
                        graph.frame(state, gen, *extra.values())

                with num_threads(threads):
                    ms = interleaved({
                        "eager": eager_frame,
                        "fast": lambda s=state, e=extra, f=fp32, g=gen: f(s, g, **e),
                        "fast_int8": lambda s=state, e=extra, f=int8, g=gen: f(s, g, **e),
                    }, repeats)  # fmt: skip
                # frames a call makes for each character: one, or the M a plan is applied for
                plan = name.startswith("camdm")
                per_call = CAMDM_M if plan else 1
                rec = {**run, "record": "speed", "model": name, "batch": batch,
                       "threads": threads, **frame_arithmetic(graph),
                       ("ms_per_plan" if plan else "ms_per_frame"): ms,
                       "speedup": round(ms["eager"] / ms["fast"], 2),
                       "speedup_int8": round(ms["eager"] / ms["fast_int8"], 2),
                       "character_frames_per_s_fast": round(batch * per_call / ms["fast"] * 1e3, 1),
                       "max_abs_diff": float(f"{diff:.2g}"), "int8_rel_rms": round(rel, 4),
                       "weights": "random" if name.startswith("paper") else "shipped",
                       "load": load()}  # fmt: skip
                results[name, batch, threads] = rec
                emit(rec, out)

    for name, goal in GOALS_MS.items():
        if (name, 1, 1) not in results:
            continue
        r = results[name, 1, 1]
        if name.startswith("camdm"):
            ms = r["ms_per_plan"]
            best = min(ms["fast"], ms["fast_int8"])
            emit({**run, "record": "goal", "model": name, "goal_ms": goal, "unit": "planning call",
                  "batch": 1, "threads": 1, "eager_ms": ms["eager"], "fast_ms": ms["fast"],
                  "fast_int8_ms": ms["fast_int8"], "met_fp32": ms["fast"] <= goal,
                  "met_int8": ms["fast_int8"] <= goal, "met": best <= goal,
                  "speedup": r["speedup"], "speedup_int8": r["speedup_int8"], "M": CAMDM_M,
                  "GFLOPs_fp32": round(r["GFLOP_per_plan_batch1"] / ms["fast"] * 1e3, 1),
                  "character_fps": {k: round(CAMDM_M / v * 1e3, 1) for k, v in ms.items()},
                  "character_fps_formula": "M / plan_ms * 1000 with M = 15 frames applied per "
                  "planning call: planning dominates (applying a planned frame is a copy), and "
                  "a re-plan at a changed input comes sooner, so this is an upper bound",
                  "load": load()}, out)  # fmt: skip
            continue
        ms = r["ms_per_frame"]
        best = min(ms["fast"], ms["fast_int8"])
        mb = r["fp32_weight_MB_per_frame"]
        emit({**run, "record": "goal", "model": name, "goal_ms": goal, "batch": 1, "threads": 1,
              "eager_ms": ms["eager"], "fast_ms": ms["fast"], "fast_int8_ms": ms["fast_int8"],
              "met_fp32": ms["fast"] <= goal, "met_int8": ms["fast_int8"] <= goal,
              "met": best <= goal,
              # weights streamed per frame / time: the bandwidth the fp32 graph achieves
              "fp32_weights_GBps": round(mb / ms["fast"], 1),
              "int8_weights_GBps": round(mb / 4 * 1.125 / ms["fast_int8"], 1),
              "GFLOPs_fp32": round(r["GFLOP_per_frame_batch1"] / ms["fast"] * 1e3, 1),
              "load": load()}, out)  # fmt: skip


if __name__ == "__main__":
    main()
