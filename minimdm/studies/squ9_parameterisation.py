"""Chapter 1's study of what the denoiser predicts: the noise, the clean sample or the velocity.

The same conditional DDPM on Squ-9 (T levels, the same network, data, seed and budget) is
trained three times, once per parameterisation of :func:`minimdm.diffusion.diffusion_loss`:

* ``eps``: the noise (A-MDM eq. 3); the clean estimate divides by :math:`\\sqrt{\\bar\\alpha_t}`,
  so an error in the noise is multiplied by :math:`\\sqrt{1/\\bar\\alpha_t - 1}`, about 400 at the
  last level of a 20-level cosine schedule;
* ``x0``: the clean sample; bounded at every level, but at the least noisy levels the network
  must rebuild its input :math:`x^t` through its layers rather than be handed it;
* ``v``: the velocity :math:`\\sqrt{\\bar\\alpha_t}\\epsilon - \\sqrt{1-\\bar\\alpha_t}x^0`
  (Salimans & Ho 2022); the clean estimate takes :math:`x^t` directly and shrinks the error.

:func:`run_seed` returns, per parameterisation, the sample quality, the largest sample and the
error of the clean estimate at every level against the ideal denoiser
(:meth:`minimdm.toy.squ9.Squ9.posterior_x0`). ``benchmarks/squ9_parameterisation.py`` runs it
for several seeds; :func:`summarize` turns the rows into mean ± std over seeds.
"""

from __future__ import annotations

from pathlib import Path

import torch

from minimdm.amdm.models import DenoiserConfig, MLPDenoiser
from minimdm.diffusion import DDPMStep, NoiseSchedule, ddpm_sample, q_sample
from minimdm.studies.seeds import read_jsonl, summarize_seeds
from minimdm.toy.squ9 import Squ9, squ9_metrics, train_denoiser

PREDICTS = ("eps", "x0", "v")
METRICS = ("coverage", "precision", "transition_tv", "max_abs")
TRAIN = dict(steps=2000, batch_size=512, lr=3e-3)
"""The budget of chapter 1's models."""


def make_denoiser(predicts: str, seed: int = 0) -> MLPDenoiser:
    """Chapter 1's denoiser (4 layers of 128, SiLU, LayerNorm) with the given output."""
    torch.manual_seed(seed)
    cfg = DenoiserConfig(x_dim=2, cond_dim=2, width=128, depth=4, time_dim=32, predicts=predicts)
    return MLPDenoiser(cfg)


@torch.no_grad()
def clean_estimate(model: MLPDenoiser, schedule: NoiseSchedule, x_t, t: int, cond):
    """The model's :math:`\\hat x^0` at level ``t``, as the sampler computes it, (B, 2)."""
    rule = DDPMStep(model, schedule, model.predicts)
    return rule.predict(x_t, t, cond, None)[0]


@torch.no_grad()
def x0_error_by_level(
    model: MLPDenoiser, schedule: NoiseSchedule, sq: Squ9, n: int = 4000, seed: int = 5
) -> tuple[list[float], list[float]]:
    """Mean squared error of the clean estimate at each level, and the ideal denoiser's.

    Fresh pairs (seed ``seed``) are noised to every level with the same noise.
    """
    g = torch.Generator().manual_seed(seed)
    x_prev, x_next = sq.sample_pairs(n, g)
    eps = torch.randn(x_next.shape, generator=g)
    model_err, ideal_err = [], []
    for t in range(schedule.T):
        x_t = q_sample(schedule, x_next, t, noise=eps)
        x0_hat = clean_estimate(model, schedule, x_t, t, x_prev)
        ideal = sq.posterior_x0(x_t, x_prev, schedule.alphas_cumprod[t])
        model_err.append(((x0_hat - x_next) ** 2).sum(-1).mean().item())
        ideal_err.append(((ideal - x_next) ** 2).sum(-1).mean().item())
    return model_err, ideal_err


def input_gain_by_level(
    model: MLPDenoiser | None, schedule: NoiseSchedule, sq: Squ9, n: int = 2000, seed: int = 5
) -> list[float]:
    """How much the clean estimate follows the noisy input, per level: the mean of
    :math:`\\tfrac12\\operatorname{tr}\\,\\partial\\hat x^0/\\partial x^t` over noised pairs.

    1 copies the input, 0 ignores it. ``model=None`` measures the ideal denoiser.
    """
    g = torch.Generator().manual_seed(seed)
    x_prev, x_next = sq.sample_pairs(n, g)
    eps = torch.randn(x_next.shape, generator=g)
    gains = []
    for t in range(schedule.T):
        x_t = q_sample(schedule, x_next, t, noise=eps).requires_grad_(True)
        with torch.enable_grad():
            if model is None:
                x0_hat = sq.posterior_x0(x_t, x_prev, schedule.alphas_cumprod[t])
            else:
                x0_hat = DDPMStep(model, schedule, model.predicts).predict(x_t, t, x_prev, None)[0]
            # samples are independent: the gradient of a column sum is each sample's Jacobian row
            diag = [
                torch.autograd.grad(x0_hat[:, i].sum(), x_t, retain_graph=True)[0][:, i]
                for i in range(2)
            ]
        gains.append((torch.stack(diag, 1).sum(1) / 2).mean().item())
    return gains


def run_seed(seed: int, T: int = 20, predicts=PREDICTS, train: dict | None = None) -> list[dict]:
    """Train one model per parameterisation with ``seed`` and measure it; one row each.

    The data are chapter 1's (training pairs from seed 0, evaluation conditions from seed 1);
    ``seed`` sets the network's initial weights, the batches, the training noise and the
    sampler's noise, so the spread over seeds is the spread of training runs.
    """
    sq = Squ9()
    x_prev, x_next = sq.sample_pairs(20_000, torch.Generator().manual_seed(0))
    x_eval, _ = sq.sample_pairs(4000, torch.Generator().manual_seed(1))
    schedule = NoiseSchedule("cosine", T)
    rows = []
    for p in predicts:
        model = make_denoiser(p, seed)
        g = torch.Generator().manual_seed(seed)
        losses = train_denoiser(model, schedule, x_prev, x_next, generator=g, **(train or TRAIN))
        with torch.no_grad():
            g_sample = torch.Generator().manual_seed(seed + 2)
            out = ddpm_sample(
                model, schedule, x_eval.shape, cond=x_eval, generator=g_sample, predicts=p
            )
        m = squ9_metrics(x_eval, out, sq)
        err, ideal = x0_error_by_level(model, schedule, sq)
        gain = input_gain_by_level(model, schedule, sq)
        rows.append(
            {
                "predicts": p,
                "seed": seed,
                "T": T,
                "coverage": m["coverage"],
                "precision": m["precision"],
                "transition_tv": m["transition_tv"],
                "max_abs": out.abs().max().item(),
                "final_loss": sum(losses[-100:]) / 100,
                "x0_err": err,
                "ideal_err": ideal,
                "input_gain": gain,
                "model": model,
                "samples": out,
            }
        )
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    """Mean ± std over seeds per parameterisation: ``{"predicts", "n_seeds", metric: (m, s)}``;
    ``x0_err_last`` is the clean estimate's error at the noisiest level."""
    rows = [{**r, "x0_err_last": r["x0_err"][-1]} for r in rows]
    return summarize_seeds(rows, "predicts", (*METRICS, "x0_err_last"))


def to_json(row: dict) -> dict:
    """A row without its model and samples, for a JSON line."""
    return {k: v for k, v in row.items() if k not in ("model", "samples")}


def read_results(path: str | Path) -> list[dict]:
    """The per-seed rows of ``benchmarks/squ9_parameterisation.py --save PATH``."""
    return read_jsonl(path, study="squ9_parameterisation")
