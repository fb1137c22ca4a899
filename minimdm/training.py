"""The one training loop of the diffusion trainers (A-MDM, CAMDM): resume, EMA, logs, checkpoints.

A trainer brings what is its own, as a :class:`Recipe`: how to draw a batch and compute its loss
(:attr:`Recipe.batch_loss`), the learning rate of a step, how to evaluate the network, and the
facts its checkpoint records. This module does the rest, the same way for every trainer:

1. :func:`start_training` builds the seeded network, its EMA copy, Adam and the batch generator,
   and loads ``out_dir``'s training state when a run is resumed;
2. :func:`train_loop` runs the plain loop below, step by step::

       lr = recipe.learning_rate(step)          # set on the optimizer
       out = recipe.batch_loss(step)            # a batch and its loss (the generator draws it)
       optimizer_step(...); ema_update(...)     # clip, step; average the weights
       every log_interval:  a record of the mean loss (and its terms) goes to log.jsonl
       every eval_interval: recipe.evaluate(the EMA network) goes to log.jsonl
       every ckpt_interval: weights + training state are saved atomically

Every random draw comes from the one generator, whose state is saved in the training state with
the weights, the EMA weights and the optimizer: a run resumed from step k takes the same step
k + 1 as an uninterrupted one, bit for bit. The log (``log.jsonl``, one JSON record a line) is
appended to, not rewritten; a resumed run drops the records past its step and a last line torn
by a kill (:func:`read_log`).
"""

from __future__ import annotations

import copy
import json
import os
import platform
import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from minimdm.checkpoint import checkpoint_paths, load_train_state, resume_training, save_checkpoint
from minimdm.files import atomic_write
from minimdm.nn import ema_update, optimizer_step, set_lr

__all__ = [
    "LoopConfig",
    "TrainState",
    "StepOut",
    "Recipe",
    "LoopResult",
    "start_training",
    "train_loop",
    "read_log",
    "trim_log",
]


class LoopConfig(Protocol):
    """The fields of a training config (a dataclass) that the shared loop reads."""

    seed: int
    lr: float
    ema_decay: float
    grad_clip: float
    total_steps: int
    log_interval: int
    eval_interval: int
    ckpt_interval: int
    config_file: str | None


@dataclass
class TrainState:
    """Everything a run needs to continue bit for bit; saved in every checkpoint."""

    model: nn.Module
    """The network being trained."""
    ema: nn.Module | None
    """Its exponential moving average (None when ``ema_decay`` is 0): what the checkpoint holds."""
    optimizer: torch.optim.Optimizer
    generator: torch.Generator
    """The source of every random draw of the loop: batches, noise levels, dropped conditions."""
    step: int = 0
    """Optimizer steps done."""
    prior_seconds: float = 0.0
    """Training time of the earlier calls this run resumes."""
    segments: list[dict] = field(default_factory=list)
    """The earlier calls that trained this run (model.json's ``segments``)."""

    @property
    def net(self) -> nn.Module:
        """The network to evaluate and ship: the EMA copy when there is one."""
        return self.ema if self.ema is not None else self.model


def start_training(
    config: LoopConfig,
    out_dir: Path,
    build: Callable[[], nn.Module],
    generator: torch.Generator,
    *,
    resume: bool,
    resumable: Iterable[str],
) -> TrainState:
    """The seeded network ``build()`` with its EMA copy, Adam and ``generator`` (seeded here by
    ``config.seed``), continued from ``out_dir``'s training state when ``resume`` and there is
    one. Resuming checks that the config equals the saved one except for the ``resumable``
    fields (budgets, intervals, device: :func:`~minimdm.checkpoint.resume_training`)."""
    with torch.random.fork_rng(devices=[]):  # the same initial weights, whatever ran before
        torch.manual_seed(config.seed)
        model = build()
    ema = copy.deepcopy(model).eval() if config.ema_decay > 0 else None
    for p in ema.parameters() if ema is not None else ():
        p.requires_grad_(False)
    opt = torch.optim.Adam(list(model.parameters()), lr=config.lr)
    state = TrainState(model, ema, opt, generator.manual_seed(config.seed))
    if resume:
        state.step, state.prior_seconds = resume_training(
            out_dir,
            asdict(config),
            model,
            opt,
            state.generator,
            ema,
            resumable=resumable,
            defaults=asdict(type(config)()),  # a field added since the run started: its default
        )
        if state.step:
            state.segments = list(load_train_state(out_dir)[0].get("segments", []))
    return state


@dataclass
class StepOut:
    """What a trainer's :attr:`Recipe.batch_loss` returns for one batch."""

    loss: Tensor
    """The scalar loss to minimize."""
    terms: dict[str, float] = field(default_factory=dict)
    """Parts of the loss: averaged over each log interval and logged beside the loss."""
    status: dict[str, float] = field(default_factory=dict)
    """Settings of this step (e.g. the student probability): logged as they are."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Facts of this step that only the per-step callback sees."""


@dataclass
class Recipe:
    """What one trainer brings to :func:`train_loop`; the loop does the rest."""

    name: str
    """The progress bar's label."""
    learning_rate: Callable[[int], float]
    """``learning_rate(step)``: the schedule, for the step about to be taken (0-based)."""
    batch_loss: Callable[[int], StepOut]
    """``batch_loss(step)``: draw a batch from the run's generator and return its loss."""
    evaluate: Callable[[nn.Module, int], dict[str, float]]
    """``evaluate(net, step)``: metrics of the network to ship (the EMA copy when there is
    one). It must leave the run's generator and the global RNG alone."""
    metadata: dict[str, Any]
    """The trainer's facts for the checkpoint (layout, skeleton, normalizer, data, ...)."""
    device: str = "cpu"
    """Recorded in each segment."""
    storage: str = "float32"
    """The sampling weights' storage (:func:`~minimdm.checkpoint.save_checkpoint`)."""
    record_segments: bool = True
    """Record each call that trained the run in the metadata (``segments``)."""
    state_order: tuple[str, ...] = ("step", "model", "ema", "optimizer", "generator")
    """The order of the training state's entries, which its file's header follows."""


@dataclass
class LoopResult:
    """What :func:`train_loop` returns."""

    step: int
    """Optimizer steps done in total."""
    start_step: int
    """The step this call started from (0, or the resumed step)."""
    seconds: float
    """Wall time of this call's loop."""
    history: list[dict]
    """The records this call logged."""


def train_loop(
    config: LoopConfig,
    out_dir: Path,
    state: TrainState,
    recipe: Recipe,
    *,
    progress: bool = True,
    callback: Callable[[int, dict[str, Any]], None] | None = None,
    is_main: bool = True,
) -> LoopResult:
    """Train ``state`` to ``config.total_steps`` with ``recipe``; log, evaluate and save into
    ``out_dir`` at the config's intervals and at the last step (see the module's docstring).

    ``callback(step, record)`` runs after every step (``step`` counts finished steps); raising
    from it stops the run, e.g. to simulate an interruption. Only the main process
    (``is_main``) writes the log and the checkpoints.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    log_path = out_dir / "log.jsonl"
    if is_main:
        trim_log(log_path, state.step)
    saver = _Saver(config, out_dir, state, recipe, is_main)
    history: list[dict] = []

    def log(record: dict) -> None:
        history.append(record)
        if is_main:
            append_log(log_path, record)

    params = list(state.model.parameters())
    start_step, sums, n = state.step, {}, 0  # sums: of the loss and its terms since the last log
    state.model.train()
    hide = not progress or not is_main
    with tqdm(total=config.total_steps, initial=state.step, disable=hide, desc=recipe.name) as bar:
        while state.step < config.total_steps:
            lr = recipe.learning_rate(state.step)
            set_lr(state.optimizer, lr)
            out = recipe.batch_loss(state.step)
            if not torch.isfinite(out.loss):
                raise FloatingPointError(
                    f"training loss became {out.loss.item()} at step {state.step}"
                )
            optimizer_step(state.optimizer, out.loss, params, config.grad_clip)
            if state.ema is not None:
                ema_update(state.ema, state.model, config.ema_decay, state.step)
            state.step += 1
            step, n = state.step, n + 1
            for k, v in {"loss": out.loss.item(), **out.terms}.items():
                sums[k] = sums.get(k, 0.0) + v
            record = {"step": step, "loss": out.loss.item(), **out.terms, **out.status, "lr": lr}
            record.update(out.extra)
            bar.update(1)
            last = step == config.total_steps
            if last or step % config.log_interval == 0:
                log({"step": step, **{k: v / n for k, v in sums.items()}, **out.status, "lr": lr})
                bar.set_postfix(loss=f"{sums['loss'] / n:.4f}", **_short(out.status))
                sums, n = {}, 0
            if last or (config.eval_interval and step % config.eval_interval == 0):
                state.net.eval()  # no dropout while it is measured (the EMA copy always is)
                metrics = recipe.evaluate(state.net, step)
                state.model.train()
                log({"step": step, **metrics})
                record.update(metrics)
            if last or (config.ckpt_interval and step % config.ckpt_interval == 0):
                saver.save()
            if callback is not None:
                callback(step, record)
    seconds = time.perf_counter() - saver.t0
    if not checkpoint_paths(out_dir).weights.exists():  # nothing to train: save the start
        saver.save()
    return LoopResult(state.step, start_step, seconds, history)


def _short(values: dict[str, float]) -> dict[str, str]:
    return {k: f"{v:.3g}" for k, v in values.items()}


class _Saver:
    """Saves the checkpoint (the EMA weights, or the raw ones) and the training state."""

    def __init__(
        self, config: LoopConfig, out_dir: Path, state: TrainState, recipe: Recipe, is_main: bool
    ) -> None:
        self.out_dir, self.state, self.recipe, self.is_main = out_dir, state, recipe, is_main
        self.metadata = {
            **recipe.metadata,
            "config": asdict(config),
            "config_file": config.config_file,
            "ema": state.ema is not None,
        }
        self.segment = {  # this call, one entry of model.json's "segments"
            "command": recipe.metadata.get("command"),
            "host": platform.node(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "threads": torch.get_num_threads(),
            "device": recipe.device,
            "from_step": state.step,
        }
        self.t0 = time.perf_counter()

    def save(self) -> None:
        """Write the checkpoint of the current step (atomically; the main process only)."""
        if not self.is_main:
            return
        s, step = self.state, self.state.step
        entries = {
            "step": step,
            "model": s.model.state_dict(),
            "ema": s.ema.state_dict() if s.ema is not None else None,
            "optimizer": s.optimizer.state_dict(),
            "generator": s.generator.get_state(),
        }
        train_state = {k: entries[k] for k in self.recipe.state_order}
        elapsed = time.perf_counter() - self.t0
        meta = dict(self.metadata, step=step, train_seconds=round(s.prior_seconds + elapsed, 1))
        if self.recipe.record_segments:  # one per call: a run may span sessions
            this = {**self.segment, "to_step": step, "seconds": round(elapsed, 1)}
            meta["segments"] = [*s.segments, this]
        save_checkpoint(self.out_dir, s.net, meta, train_state, storage=self.recipe.storage)


# --------------------------------------------------------------------------------------------
# The log: one JSON record a line.


def read_log(path: str | os.PathLike) -> list[tuple[str, dict]]:
    """The records of a training log (``log.jsonl``), each with its line of text.

    A process killed while appending leaves a torn last line: it is skipped with a warning that
    names the file (the training state, written atomically, is intact). A bad line elsewhere is
    no kill's doing and raises a ``ValueError`` naming the file and the line.
    """
    path = Path(path)
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    out = []
    for i, ln in enumerate(lines, start=1):
        try:
            rec = json.loads(ln)
            if not isinstance(rec, dict) or not isinstance(rec.get("step"), int):
                raise ValueError("a record must be a JSON object with an integer 'step'")
        except ValueError as e:
            if i == len(lines):
                warnings.warn(
                    f"{path}:{i}: skipping a torn last log line (a run killed while writing "
                    f"it?): {ln[:60]!r}",
                    stacklevel=2,
                )
                break
            raise ValueError(
                f"{path}:{i}: expected a JSON log record with a 'step', got {ln[:60]!r} ({e}); "
                "fix or delete that line to resume"
            ) from None
        out.append((ln, rec))
    return out


def trim_log(path: Path, step: int) -> None:
    """Keep only the records of steps up to ``step`` (where a resumed run continues), and drop
    a last line torn by a kill; the log is rewritten atomically. No log: nothing to do."""
    if path.exists():
        keep = [ln for ln, rec in read_log(path) if rec["step"] <= step]
        atomic_write(path, "".join(ln + "\n" for ln in keep))


def append_log(path: Path, record: dict) -> None:
    """Append one record to the log."""
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")
