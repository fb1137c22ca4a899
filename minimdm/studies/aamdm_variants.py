"""AAMDM's two pair constructions on Squ-9, side by side over seeds (chapter 8).

AAMDM's Algorithm 1 (lines 20-24) makes the discriminator's pairs differently from DD-GAN
(Xiao et al. 2022), which the library's default follows (see :mod:`minimdm.aamdm.train`):

=========  ==========================================  ==========================================
variant    real pair :math:`(x^{t-1}, x^t)`             fake :math:`x^{t-1}`
=========  ==========================================  ==========================================
``ddgan``  the data, forward-diffused                  posterior :math:`q(x^{t-1}|x^t,\\hat x^0)`
``paper``  the polisher's output, forward-diffused     :math:`q(x^{t-1}|\\hat x^0)` (line 24)
           (line 20)
=========  ==========================================  ==========================================

:func:`compare_pairs` trains, for every seed, one polisher with
:class:`~minimdm.studies.squ9_acceleration.Squ9Study` and then one generator per variant from the
same initial weights (a paired design: the seed sets the data, the weights and the training
noise, and only the pair construction differs), and measures each AAMDM (3 + 2) with
:meth:`Squ9Study.evaluate`. :func:`summarize` turns the
per-seed rows into mean ± std per variant and the paired difference; :func:`describe` words it,
so that the book's prose is computed from the numbers.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from minimdm.aamdm.model import StepCount
from minimdm.aamdm.train import PAIRS
from minimdm.motion.metrics import mean_std
from minimdm.studies.squ9_acceleration import Squ9Study, Squ9StudyConfig

__all__ = [
    "VARIANT_LABELS",
    "METRICS",
    "VariantsConfig",
    "compare_pairs",
    "summarize",
    "describe",
    "read_results",
]

VARIANT_LABELS = {
    "ddgan": "DD-GAN pairs (data, posterior)",
    "paper": "Algorithm 1 pairs (polisher, FD)",
}
"""Table labels of the pair constructions."""
METRICS = {
    "coverage": "higher",
    "precision": "higher",
    "transition_tv": "lower",
    "gan_train_cpu_s": "lower",
    "cpu_ms_per_step": "lower",
}
"""The compared numbers and which direction is better. Times are CPU seconds of this process
(``time.process_time``), which a busy machine disturbs far less than wall-clock times."""


@dataclass
class VariantsConfig:
    """Seeds and training budgets of the comparison (smaller than the chapter's main study)."""

    seeds: tuple[int, ...] = (0, 1, 2)
    """One full run (data, weights, training) per seed."""
    variants: tuple[str, ...] = PAIRS
    """The pair constructions compared (``GANConfig.pairs`` values)."""
    gan_steps: int = 1500
    """DD-GAN training steps of each variant."""
    polish_steps: int = 300
    """Polisher training steps (one polisher per seed, shared by the variants)."""
    repeats: int = 3
    """Timed sampling repeats; the fastest counts."""
    study: Squ9StudyConfig = field(default_factory=Squ9StudyConfig)
    """Data, sizes and every other training setting (its seed and step counts are replaced)."""

    def __post_init__(self) -> None:
        bad = [v for v in self.variants if v not in PAIRS]
        if bad or not self.variants:
            raise ValueError(f"variants must be a non-empty subset of {PAIRS}, got {self.variants}")
        if not self.seeds:
            raise ValueError("seeds must hold at least one seed")


def compare_pairs(
    config: VariantsConfig | None = None, device: str = "cpu", progress: bool = False
) -> list[dict]:
    """Train and evaluate every variant for every seed; one row per (seed, variant).

    A row holds ``seed``, ``variant``, ``label``, ``coverage``, ``precision``,
    ``transition_tv``, ``network_calls``, the sampling time per network call for the whole
    evaluation batch (``ms_per_step`` wall clock, from :meth:`Squ9Study.evaluate`;
    ``cpu_ms_per_step`` process CPU time, timed after all variants of the seed are trained,
    the variants taking turns, the fastest of ``repeats`` runs each), the generator's training
    time (``gan_train_s`` wall, ``gan_train_cpu_s`` CPU) and the shared polisher's
    (``polish_train_s`` wall).
    """
    config = config or VariantsConfig()
    rows = []
    for seed in config.seeds:
        base = config.study
        study = Squ9Study(
            replace(
                base,
                seed=seed,
                gan=replace(base.gan, steps=config.gan_steps, seed=seed),
                polish=replace(base.polish, steps=config.polish_steps, seed=seed),
            ),
            device,
        )
        if progress:
            print(f"seed {seed}: training the polisher ...", flush=True)
        first = study.build_aamdm()
        polish_s = study.train_polisher(first)
        models, seed_rows = {}, []
        for variant in config.variants:
            if progress:
                print(f"seed {seed}: training the generator, pairs={variant!r} ...", flush=True)
            model = study.build_aamdm()  # the same initial weights for every variant
            model.polisher.load_state_dict(first.polisher.state_dict())
            model.polisher.eval()
            cpu0 = time.process_time()
            gan_s = study.train_generator(model, replace(study.config.gan, pairs=variant))
            gan_cpu = time.process_time() - cpu0
            study.models["aamdm"] = model.eval()
            study.train_seconds["aamdm"] = gan_s
            (r,), _ = study.evaluate(("aamdm",), repeats=config.repeats)
            models[variant] = model
            seed_rows.append(
                {
                    "seed": seed,
                    "variant": variant,
                    "label": VARIANT_LABELS[variant],
                    **{k: r[k] for k in ("coverage", "precision", "transition_tv")},
                    "network_calls": r["network_calls"],
                    "ms_per_step": r["ms_per_step"],
                    "gan_train_s": round(gan_s, 2),
                    "gan_train_cpu_s": round(gan_cpu, 2),
                    "polish_train_s": round(polish_s, 2),
                }
            )
        cpu_ms = _cpu_ms_per_step(models, study.x_eval, config.repeats)
        rows += [{**r, "cpu_ms_per_step": round(cpu_ms[r["variant"]], 4)} for r in seed_rows]
    return rows


@torch.no_grad()
def _cpu_ms_per_step(models: dict, cond, repeats: int) -> dict[str, float]:
    """Process CPU milliseconds per network call of one AAMDM sample of ``cond`` for each
    model, fastest run. The models take turns (the order reversed every round), so that a
    drift of the machine's load or clock hits them alike."""
    best = dict.fromkeys(models, float("inf"))
    calls = {}
    names = list(models)
    for i in range(max(1, repeats) + 1):  # round 0 warms up and is not counted
        for name in names if i % 2 else names[::-1]:
            count, g = StepCount(), torch.Generator(cond.device).manual_seed(2)
            t0 = time.process_time()
            models[name].sample(cond, g, count=count)
            if i:
                best[name] = min(best[name], time.process_time() - t0)
            calls[name] = count.network_calls
    return {name: 1000 * best[name] / calls[name] for name in names}


def summarize(rows: list[dict], reference: str = "ddgan") -> list[dict]:
    """Mean ± std over seeds per variant, then the paired difference of each other variant.

    Returns rows ``{"model": name, "n_seeds": n, metric: (mean, std), ...}`` for
    :func:`minimdm.utils.format_table`: one per variant, then ``"<variant> - <reference>"``
    with the mean and std of the per-seed differences (seeds present in both).
    """
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    by = {v: {r["seed"]: r for r in rows if r["variant"] == v} for v in variants}
    out = []
    for v in variants:
        out.append(
            {
                "model": VARIANT_LABELS.get(v, v),
                "variant": v,
                "n_seeds": len(by[v]),
                **{m: mean_std(r[m] for r in by[v].values()) for m in METRICS},
            }
        )
    if reference in by:
        for v in variants:
            if v == reference:
                continue
            seeds = sorted(set(by[v]) & set(by[reference]))
            out.append(
                {
                    "model": f"{v} - {reference}",
                    "variant": f"{v}-{reference}",
                    "n_seeds": len(seeds),
                    **{
                        m: mean_std(by[v][s][m] - by[reference][s][m] for s in seeds)
                        for m in METRICS
                    },
                }
            )
    return out


def describe(summary: list[dict], a: str = "paper", b: str = "ddgan", digits: int = 2) -> str:
    """One sentence per metric comparing variants ``a`` and ``b`` from :func:`summarize` rows.

    A difference counts as beyond the seed spread when the intervals mean ± std of the two
    variants do not overlap; otherwise the sentence says the seeds cannot separate them.
    """
    rows = {r["variant"]: r for r in summary}
    if a not in rows or b not in rows:
        raise ValueError(f"summary must hold variants {a!r} and {b!r}, got {sorted(rows)}")
    la, lb = VARIANT_LABELS.get(a, a), VARIANT_LABELS.get(b, b)
    n = min(rows[a]["n_seeds"], rows[b]["n_seeds"])
    lines = []
    for m, better in METRICS.items():
        (ma, sa), (mb, sb) = rows[a][m], rows[b][m]
        nums = f"{la} {ma:.{digits}f} ± {sa:.{digits}f}, {lb} {mb:.{digits}f} ± {sb:.{digits}f}"
        if abs(ma - mb) <= sa + sb:
            verdict = f"the intervals overlap, so {n} seeds cannot separate the two"
        else:
            win = la if (ma > mb) == (better == "higher") else lb
            verdict = f"{win} is better, beyond the seed spread"
        lines.append(f"{m} ({better} is better): {nums}; {verdict}.")
    return "\n".join(lines)


def read_results(path: str | Path) -> tuple[list[dict], dict, dict]:
    """The per-seed rows, the config and the hardware of a ``benchmarks/squ9_acceleration.py
    --pairs --out PATH`` run (its ``"kind": "seed"`` lines), ready for :func:`summarize`."""
    lines = [json.loads(x) for x in Path(path).read_text().splitlines() if x.strip()]
    seeds = [x for x in lines if x.get("study") == "squ9_aamdm_pairs" and x.get("kind") == "seed"]
    if not seeds:
        raise ValueError(
            f"{path} holds no squ9_aamdm_pairs seed lines; run the benchmark with --pairs"
        )
    drop = ("study", "kind", "config", "hardware")
    rows = [{k: v for k, v in x.items() if k not in drop} for x in seeds]
    return rows, seeds[0]["config"], seeds[0]["hardware"]
