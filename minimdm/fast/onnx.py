"""One frame as one ONNX graph: export with metadata, and :class:`FastFrame`, the fast path.

:func:`export_onnx` traces a :class:`~minimdm.fast.graphs.FrameGraph` (the model's own eager
frame step, noise as an input) with PyTorch's TorchScript-based ONNX exporter: the Python loop
over denoising levels unrolls into one graph, the level-dependent schedule values and time
embeddings become constants, and the batch stays a free dimension. The file carries the weights
and, under the metadata key ``minimdm``, one JSON object (:func:`read_metadata`) with what a
game engine needs: the inputs and their meaning, the noise layout, the sampler and its
schedule, the normalizer, the feature layout, the skeleton and the frame rate. A CAMDM planning
call (:class:`~minimdm.fast.graphs.CAMDMPlan`) is exported the same way: its inputs are the past
frames, the style index (int64), the trajectory, the CFG scale and the noise, its output the
future frames; its metadata adds P, F, T, the guide and the styles (in ``feature_layout``).

:class:`FastFrame` runs that graph in an ONNX Runtime inference session. It is a drop-in for the
eager per-frame step, ``frame = fast(state, generator)``: it draws the frame's noise from the
generator exactly as the eager chain would (:meth:`~minimdm.diffusion.NoiseTape.draw`), so the
same seed gives the same frames within float rounding (tests: 1e-4). Pass it as ``fast=`` to
:func:`minimdm.amdm.sampling.rollout` or :func:`minimdm.aamdm.eval.rollout_aamdm`, or use
:meth:`FastFrame.step` with :func:`~minimdm.amdm.sampling.autoregress`.

Why ONNX Runtime: it was the fastest engine measured for one frame at batch 1, and its file is
also what a game engine loads (the measurements: the book's *Performance* page and
``benchmarks/results/realtime.jsonl``).
"""

from __future__ import annotations

import json
import os
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from minimdm._version import __version__
from minimdm.files import atomic_write
from minimdm.validate import MAX_FEATURE, InputError, InputTypeError, check_int, describe

from .graphs import FrameGraph

__all__ = [
    "CAMDMPlanner",
    "fast_planner",
    "FORMAT",
    "METADATA_KEY",
    "WEIGHTS",
    "metadata",
    "export_onnx",
    "read_metadata",
    "FastFrame",
    "fast_frame",
]

FORMAT = "minimdm-frame-onnx/1"
"""The ``format`` field of the metadata; bumped when its meaning changes."""
METADATA_KEY = "minimdm"
"""The ONNX ``metadata_props`` key that holds the JSON metadata."""
OPSET = 17
"""ONNX opset of the exported graphs (LayerNormalization is native from 17 on)."""


def _require_onnxruntime():
    try:
        import onnxruntime
    except ImportError:  # pragma: no cover - a dependency of minimdm
        raise ImportError(
            "the fast path needs onnxruntime: pip install onnxruntime (a minimdm dependency)"
        ) from None
    return onnxruntime


def metadata(graph: FrameGraph, weights: str = "fp32", batch: int | None = None) -> dict[str, Any]:
    """The JSON metadata of ``graph``'s ONNX file (module docstring)."""
    b = "batch" if batch is None else int(batch)
    inputs = [_port(p, b) for p in graph.inputs()]
    noise = {
        "name": "noise",
        "shape": [b, graph.noise_dim],
        "what": "standard normal noise: one block of columns per draw of the chain, in order",
        "widths": list(graph.noise_widths),
    }
    inputs.append(noise)
    return {
        "format": FORMAT,
        "kind": graph.kind,
        "minimdm_version": __version__,
        "inputs": inputs,
        "outputs": [_port(graph.output(), b)],
        "weights": weights,
        **graph.describe(),
        **graph.settings,
    }


def _port(p, batch: int | str) -> dict[str, Any]:
    """An input or output in the metadata: name, shape with the batch, meaning, dtype."""
    d: dict[str, Any] = {"name": p.name, "shape": [batch, *p.shape]}
    if p.what:
        d["what"] = p.what
    if p.dtype != "float32":
        d["dtype"] = p.dtype
    if p.classes is not None:
        d["classes"] = p.classes
    return d


WEIGHTS = ("fp32", "int8")
"""The weight formats :func:`export_onnx` writes."""
MAX_BATCH = 1 << 16
"""The largest fixed batch :func:`export_onnx` traces."""


def export_onnx(
    graph: FrameGraph,
    path: str | os.PathLike | None = None,
    weights: str = "fp32",
    batch: int | None = None,
) -> bytes:
    """Trace ``graph`` into one ONNX graph with its metadata; write it to ``path`` if given.

    ``weights="int8"`` stores every linear layer's weights as 8-bit integers with one fp32 scale
    per block of 32 inputs (ONNX Runtime's ``MatMulNBits``, computed with int8 dot products):
    a quarter of the bytes, so that a large denoiser stays in the CPU's cache. It is an
    approximation: on the same noise a frame differs from the fp32 graph's by 1 to 9 % of its
    RMS, more with DDIM's few steps (``benchmarks/realtime.py`` measures it); ``"fp32"`` matches
    the eager chain within 1e-4.
    ``batch`` None leaves the batch free; a number fixes it, which lets the exporter fold
    everything that depends only on the level (time embeddings and their MLP, schedule values)
    into constants: fewer operations per frame, e.g. for one character in a browser.
    The write is atomic (a temporary file, then a rename). Returns the model's bytes.
    """
    if weights not in WEIGHTS:
        raise InputError(f"weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
    if not isinstance(graph, FrameGraph):
        raise InputTypeError(
            f"graph must be a FrameGraph (minimdm.fast.frame_graph), got {describe(graph)}"
        )
    if batch is not None:  # 0 would divide by zero inside the exporter (SIGFPE)
        batch = check_int("batch", batch, low=1, high=MAX_BATCH)
    graph = graph.eval()
    args = graph.example_inputs(batch=1 if batch is None else int(batch))
    names = [*(p.name for p in graph.inputs()), "noise"]
    output = graph.output().name
    axes = {n: {0: "batch"} for n in [*names, output]} if batch is None else None
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        # The chain's input checks run once at trace time on the example inputs; the graph keeps
        # none of them (FastFrame checks its inputs before every call).
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX export.*")
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        # index_add (the residual hook) always warns; its indices are distinct features
        warnings.filterwarnings("ignore", message=".*duplicated values in 'index' field.*")
        f = Path(tmp) / "frame.onnx"
        # A transformer (CAMDM) in eval mode runs PyTorch's fused encoder-layer kernel, which has
        # no ONNX form; without it the same layer traces into plain operations.
        fused = torch.backends.mha.get_fastpath_enabled()
        torch.backends.mha.set_fastpath_enabled(False)
        try:
            torch.onnx.export(
                graph,
                args,
                str(f),
                dynamo=False,
                input_names=names,
                output_names=[output],
                dynamic_axes=axes,
                opset_version=OPSET,
                do_constant_folding=True,
            )
        finally:
            torch.backends.mha.set_fastpath_enabled(fused)
        import onnx

        model = onnx.load(str(f))
    if weights == "int8":
        model = _int8_weights(model)
    meta = model.metadata_props.add()
    meta.key, meta.value = METADATA_KEY, json.dumps(metadata(graph, weights, batch))
    model.producer_name, model.producer_version = "minimdm", __version__
    data = model.SerializeToString()
    if path is not None:
        atomic_write(path, data)
    return data


def _int8_weights(model):
    """The graph with every linear layer's weights in blocks of 8-bit integers (MatMulNBits).

    The tracer writes a linear layer as ``Gemm(x, W, b, transB=1)``; ONNX Runtime's weight
    quantizer takes ``MatMul`` nodes, so each becomes ``MatMul(x, W^T) + b`` first. The exporter
    shares a weight between denoising steps through ``Identity`` nodes (a transformer's layers
    on (B, n, L) tokens: ``MatMul`` with a folded ``W^T``); the quantizer only takes a weight
    that is an initializer, so every such alias is read through first.
    """
    import logging

    from onnx import helper, numpy_helper
    from onnxruntime.quantization.matmul_nbits_quantizer import MatMulNBitsQuantizer

    g = model.graph
    names = {i.name for i in g.initializer}
    alias = {
        n.output[0]: n.input[0] for n in g.node if n.op_type == "Identity" and n.input[0] in names
    }
    alias = {k: v for k, v in alias.items() if k not in {o.name for o in g.output}}
    for n in g.node:
        for k, x in enumerate(n.input):
            if x in alias:
                n.input[k] = alias[x]
    _keep_used(g, [n for n in g.node if n.op_type != "Identity" or n.output[0] not in alias])
    tensors = {i.name: numpy_helper.to_array(i) for i in g.initializer}
    constants = {
        n.output[0]: numpy_helper.to_array(n.attribute[0].t)
        for n in g.node
        if n.op_type == "Constant" and n.attribute[0].name == "value"
    }
    tensors.update(constants)
    nodes, made = [], set()
    for n in g.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in n.attribute}
        plain = attrs.get("alpha", 1.0) == 1.0 and attrs.get("beta", 1.0) == 1.0
        if n.op_type != "Gemm" or n.input[1] not in tensors or attrs.get("transA") or not plain:
            nodes.append(n)
            continue
        name = f"{n.input[1]}.t" if attrs.get("transB") else n.input[1]
        if name not in made and name not in tensors:  # once per weight, not once per step
            w = tensors[n.input[1]].T
            g.initializer.append(numpy_helper.from_array(np.ascontiguousarray(w), name))
            made.add(name)
        product = f"{n.output[0]}.matmul" if len(n.input) > 2 else n.output[0]
        nodes.append(helper.make_node("MatMul", [n.input[0], name], [product]))
        if len(n.input) > 2:
            nodes.append(helper.make_node("Add", [product, n.input[2]], [n.output[0]]))
    _keep_used(g, nodes)
    log = logging.getLogger("onnxruntime.quantization.matmul_nbits_quantizer")
    level = log.level
    log.setLevel(logging.WARNING)
    try:
        q = MatMulNBitsQuantizer(model, bits=8, block_size=32, is_symmetric=True, accuracy_level=4)
        q.process()
    finally:
        log.setLevel(level)
    model = q.model.model
    _keep_used(model.graph, list(model.graph.node))
    return model


def _keep_used(g, nodes: list) -> None:
    """Set the graph's nodes to ``nodes`` less the constants and initializers nothing reads."""
    used = {i for n in nodes for i in n.input} | {o.name for o in g.output}
    nodes = [n for n in nodes if n.op_type != "Constant" or n.output[0] in used]
    del g.node[:]
    g.node.extend(nodes)
    seen: set[str] = set()  # the quantizer writes a shared weight once per node that reads it
    keep = [i for i in g.initializer if i.name in used and not (i.name in seen or seen.add(i.name))]
    del g.initializer[:]
    g.initializer.extend(keep)


def read_metadata(model: str | os.PathLike | bytes) -> dict[str, Any]:
    """The JSON metadata of an exported frame graph (a path or the model's bytes).

    Raises:
        InputError: the file is not an exported minimdm frame graph.
    """
    ort = _require_onnxruntime()
    where = "the model bytes" if isinstance(model, bytes) else str(model)
    try:
        sess = ort.InferenceSession(
            model if isinstance(model, bytes) else str(model), providers=["CPUExecutionProvider"]
        )
    except Exception as e:  # onnxruntime raises its own exception types
        raise InputError(f"{where} is not a readable ONNX model: {e}") from None
    return _metadata_of(sess, where)


def _metadata_of(sess, where: str) -> dict[str, Any]:
    props = sess.get_modelmeta().custom_metadata_map
    if METADATA_KEY not in props:
        raise InputError(
            f"{where} has no {METADATA_KEY!r} metadata: it was not written by minimdm export"
        )
    meta = json.loads(props[METADATA_KEY])
    if meta.get("format") != FORMAT:
        raise InputError(f"{where} has metadata format {meta.get('format')!r}, expected {FORMAT!r}")
    return meta


class FastFrame:
    """A frame graph in an ONNX Runtime session: ``next_state = fast(state, generator)``.

    Args:
        model: an exported graph (its bytes or a path), or a :class:`FrameGraph` to export.
        threads: ONNX Runtime intra-op threads (1: the fastest for one character; None: all
            cores).

    The call takes ``state`` (B, S) and the ``extra`` inputs by name (a policy's ``task``), and
    either a ``generator`` (the noise is drawn from it as the eager chain draws it) or the
    ``noise`` (B, N) itself. It returns a float32 tensor on the CPU. A graph with other inputs
    takes its first one in ``state``'s place: a CAMDM plan is ``future = fast(past, generator,
    style=, trajectory=, gamma=)``, the drop-in ``planner`` of
    :class:`~minimdm.camdm.controller.CAMDMController`.
    """

    def __init__(self, model: FrameGraph | bytes | str | os.PathLike, threads: int | None = 1):
        ort = _require_onnxruntime()
        if isinstance(model, FrameGraph):
            model = export_onnx(model)
        where = "the model bytes" if isinstance(model, bytes) else str(model)
        opts = ort.SessionOptions()
        if threads is not None:
            opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.log_severity_level = 3  # no warnings on stderr
        src = model if isinstance(model, bytes) else str(model)
        self.session = ort.InferenceSession(src, opts, providers=["CPUExecutionProvider"])
        self.metadata = _metadata_of(self.session, where)
        ins = self.metadata["inputs"]
        self.inputs = [i["name"] for i in ins]
        self.shapes: dict[str, tuple[int, ...]] = {i["name"]: tuple(i["shape"][1:]) for i in ins}
        """Each input's shape after the batch."""
        self.dtypes: dict[str, str] = {i["name"]: i.get("dtype", "float32") for i in ins}
        self.classes: dict[str, int] = {i["name"]: i["classes"] for i in ins if "classes" in i}
        """Integer inputs' numbers of classes (CAMDM's style): indices lie in [0, classes)."""
        self.noise_widths = tuple(ins[-1]["widths"])
        self.kind = self.metadata["kind"]

    @property
    def state_dim(self) -> int:
        """The last dimension of the first input (S for a frame, D for a CAMDM plan)."""
        return self.shapes[self.inputs[0]][-1]

    def noise(self, batch: int, generator: torch.Generator | None = None) -> Tensor:
        """(batch, N) one frame's noise, drawn as the eager chain draws it."""
        from minimdm.diffusion import NoiseTape

        return NoiseTape.draw(self.noise_widths, batch, generator)

    def _array(self, name: str, x: Any, batch: int | None) -> np.ndarray:
        """The input ``name`` as a contiguous array, checked as the eager step checks it: its
        shape, integer indices within their range, floats finite and within ±MAX_FEATURE."""
        if not isinstance(x, (Tensor, np.ndarray)):
            raise InputTypeError(f"{name} must be a tensor, got {type(x).__name__}")
        a = x.detach().cpu().numpy() if isinstance(x, Tensor) else x
        shape = self.shapes[name]
        if a.shape[1:] != shape or a.ndim == 0 or (batch is not None and a.shape[0] != batch):
            want = ", ".join(map(str, (batch if batch is not None else "B", *shape)))
            want = f"({want},)" if not shape else f"({want})"
            raise InputError(f"{name} must have shape {want}, got {tuple(a.shape)}")
        if self.dtypes[name] == "int64":
            if not np.issubdtype(a.dtype, np.integer):
                raise InputTypeError(f"{name} must hold integers (indices), got {a.dtype}")
            n = self.classes.get(name)
            if n is not None and a.size and not (0 <= a.min() and a.max() < n):
                bad = int(a.flat[np.flatnonzero((a < 0) | (a >= n))[0]])
                raise InputError(f"{name} must hold indices in [0, {n - 1}], got {bad}")
            return np.ascontiguousarray(a.astype(np.int64, copy=False))
        if a.dtype == np.bool_ or not np.issubdtype(a.dtype, np.number):
            raise InputTypeError(f"{name} must hold numbers, got {a.dtype}")
        a = a.astype(np.float32, copy=False)
        if not np.isfinite(a).all():
            raise InputError(f"{name} must be finite, but it holds NaN/Inf")
        if a.size and np.abs(a).max() > MAX_FEATURE:
            where = np.unravel_index(int(np.argmax(np.abs(a))), a.shape)
            raise InputError(
                f"{name} must hold values within ±{MAX_FEATURE:g} (as the eager step checks), "
                f"but {name}{list(map(int, where))} is {float(a[where]):.3g}"
            )
        return np.ascontiguousarray(a)

    def __call__(
        self,
        state: Tensor,
        generator: torch.Generator | None = None,
        *,
        noise: Tensor | None = None,
        **extra: Tensor,
    ) -> Tensor:
        """The next state (B, S) from ``state`` (B, S); see the class docstring."""
        first = self.inputs[0]
        feed = {first: self._array(first, state, None)}
        B = feed[first].shape[0]
        missing = [n for n in self.inputs[1:-1] if n not in extra]
        unknown = sorted(set(extra) - set(self.inputs[1:-1]))
        if missing or unknown:
            raise InputError(
                f"a {self.kind} graph takes the inputs {self.inputs[1:-1]} besides {first} and "
                f"noise; missing {missing}, unknown {unknown}"
            )
        for n in self.inputs[1:-1]:
            feed[n] = self._array(n, extra[n], B)
        if noise is None:
            noise = self.noise(B, generator)
        feed["noise"] = self._array("noise", noise, B)
        (out,) = self.session.run(None, feed)
        return torch.from_numpy(out)

    def step(self, generator: torch.Generator | None = None, **extra: Any) -> Callable:
        """``step(f, x_prev) -> x_f`` for :func:`~minimdm.amdm.sampling.autoregress`.

        An extra input may be a tensor or a function ``(f, x_prev) -> tensor`` of the frame.
        """

        def step(f: int, x_prev: Tensor) -> Tensor:
            args = {k: (v(f, x_prev) if callable(v) else v) for k, v in extra.items()}
            return self(x_prev, generator, **args)

        return step


class CAMDMPlanner:
    """CAMDM's planning calls on two graphs, each plan on the cheaper one that computes it.

    ``conditional`` is the graph of the conditional model alone (``guide="none"``), ``guided``
    one of both halves of eq. 5 (:class:`~minimdm.fast.graphs.CAMDMPlan`). A call whose every
    ``gamma`` is 1 runs on ``conditional``, half the rows; any other on ``guided``. The
    controller plans at ``gamma = 1`` except in the second after a style change, so most plans
    cost half. Both graphs draw the noise from the generator as the eager chain does, which also
    runs the conditional model alone at ``gamma = 1``: the same frames within float rounding.
    ``calls`` counts the plans each graph served. A drop-in ``planner`` of
    :class:`~minimdm.camdm.controller.CAMDMController`; its ``metadata`` is the guided graph's.
    """

    def __init__(self, guided: FastFrame, conditional: FastFrame) -> None:
        for name, f, guides in (
            ("guided", guided, ("past", "style", "each")),
            ("conditional", conditional, ("none",)),
        ):
            if not isinstance(f, FastFrame):
                raise InputTypeError(f"{name} must be a FastFrame, got {type(f).__name__}")
            got = (f.kind, f.metadata.get("plan", {}).get("guide"))
            if f.kind != "camdm" or got[1] not in guides:
                raise InputError(
                    f"{name} must be a CAMDM plan graph with guide in {guides}, got kind and "
                    f"guide {got}"
                )
        a, b = (dict(f.metadata["plan"], guide=None) for f in (guided, conditional))
        if a != b or guided.noise_widths != conditional.noise_widths:
            raise InputError(f"the two graphs plan differently: guided {a}, conditional {b}")
        self.guided, self.conditional = guided, conditional
        self.metadata = guided.metadata
        self.calls = {"conditional": 0, "guided": 0}

    def __call__(
        self,
        past: Tensor,
        generator: torch.Generator | None = None,
        *,
        style: Tensor,
        trajectory: Tensor,
        gamma: Tensor,
        on_style: Tensor | None = None,
        noise: Tensor | None = None,
    ) -> Tensor:
        """The future (B, F, D), as :class:`FastFrame` computes it on the chosen graph.
        ``on_style`` (B,) (1: CFG on the style, 0: on the past) is for a guided graph of
        ``guide="each"``, which needs it."""
        if bool((torch.as_tensor(gamma) == 1).all()):
            self.calls["conditional"] += 1
            return self.conditional(
                past, generator, noise=noise, style=style, trajectory=trajectory
            )
        self.calls["guided"] += 1
        each = self.metadata["plan"]["guide"] == "each"
        if each != (on_style is not None):
            raise InputError(
                "on_style: the guided graph of guide='each' needs it, any other takes none; got "
                f"guide {self.metadata['plan']['guide']!r} and on_style {describe(on_style)}"
            )
        more = {"on_style": torch.as_tensor(on_style).long()} if each else {}
        return self.guided(
            past, generator, noise=noise, style=style, trajectory=trajectory, gamma=gamma, **more
        )


def fast_planner(
    checkpoint: Any, threads: int | None = 1, weights: str = "fp32", guide: str = "past"
) -> CAMDMPlanner:
    """The :class:`CAMDMPlanner` of a CAMDM checkpoint (a loaded one, a path or a shipped name):
    its conditional graph and its graph guided on ``guide`` ('past', 'style', or 'each': per
    sample, for a controller with ``guide_switch``); ``threads`` and ``weights`` as in
    :func:`fast_frame`."""
    from .graphs import frame_graph, load

    ckpt = load(checkpoint)
    if ckpt.kind != "camdm":
        raise InputError(f"fast_planner needs a CAMDM checkpoint (kind camdm), got {ckpt.kind!r}")
    if guide == "none":
        raise InputError("guide: the planner's guided graph needs 'past' or 'style', got 'none'")
    guided, conditional = (
        FastFrame(export_onnx(frame_graph(ckpt, guide=g), weights=weights), threads)
        for g in (guide, "none")
    )
    return CAMDMPlanner(guided, conditional)


def fast_frame(
    checkpoint: Any,
    steps: int | None = None,
    eta: float = 1.0,
    threads: int | None = 1,
    weights: str = "fp32",
    **options: Any,
) -> FastFrame:
    """The :class:`FastFrame` of a checkpoint (a loaded one, a path or a shipped name).

    ``steps`` and ``eta`` pick DDIM for A-MDM, as in :func:`minimdm.amdm.sampling.rollout`;
    ``weights`` as in :func:`export_onnx`; ``options`` as in
    :func:`~minimdm.fast.graphs.frame_graph` (CAMDM: ``guide``).
    """
    from .graphs import frame_graph

    graph = frame_graph(checkpoint, steps, eta, **options)
    return FastFrame(export_onnx(graph, weights=weights), threads)
