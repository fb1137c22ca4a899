"""The Squ-9 acceleration study: AAMDM §4.2 (Figure 3) and the ablations of §4.3 (Table 2).

:class:`Squ9Study` trains every model of the comparison on the same Squ-9 data with fixed seeds,
samples one transition per evaluation condition, and measures each with
:func:`~minimdm.toy.squ9.squ9_metrics` and a clock:

=============  ==============================================================  =============
method         model                                                           network calls
=============  ==============================================================  =============
``mse``        deterministic regressor (the one-to-one map of LMM)            1
``mvae``       MVAE-style conditional VAE, z from the prior                    1
``ddpm5``      DDPM, eps-prediction, cosine schedule, T = 5                    5
``ddpm200``    the same with T = 200                                           200
``adm5``       the polishing model alone: x0-prediction, Gaussian steps over   5
               the whole AAMDM schedule (Algorithm 1 with T_ADM = 5)
``ddgan``      DD-GAN alone: the generation module, its last x0 estimate       3
``aamdm``      AAMDM: 3 DD-GAN steps, then 2 polishing steps                   5
=============  ==============================================================  =============

``ms_per_step`` is the wall time of sampling the whole evaluation batch divided by the number of
network calls of the chain; ``speedup_vs_ddpm200`` is DDPM-200's time for that batch over the
method's, measured in the same run. :meth:`Squ9Study.ablation` retrains what each
(T_GAN, T_ADM) setting needs: one generator per T_GAN (the polisher of the main run serves
every T_GAN, since the polishing levels of :func:`~minimdm.aamdm.model.aamdm_betas` do not depend on
it) and one polisher per T_ADM (the main run's generator serves every T_ADM, its hand-over level
being fixed).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor, nn

from minimdm.aamdm.model import (
    AAMDM,
    AAMDMConfig,
    DDGANDiscriminator,
    DiscriminatorConfig,
    StepCount,
    aamdm_schedule,
)
from minimdm.aamdm.train import (
    GANConfig,
    PolishConfig,
    pairs_to_windows,
    train_ddgan,
    train_polisher,
)
from minimdm.amdm.models import MVAE, DenoiserConfig, MLPDenoiser, MLPRegressor, MVAEConfig
from minimdm.amdm.sampling import autoregress
from minimdm.checkpoint import load_checkpoint, save_checkpoint
from minimdm.diffusion import NoiseSchedule, data_range, ddpm_sample
from minimdm.nn import optimizer_step
from minimdm.toy.squ9 import Squ9, squ9_metrics, train_denoiser, train_regressor

__all__ = ["METHODS", "PANELS", "LABELS", "Squ9StudyConfig", "Squ9Study", "with_budget"]

METHODS = ("mse", "mvae", "ddpm5", "ddpm200", "adm5", "ddgan", "aamdm")
"""Every method of the study, in table order."""
PANELS = ("mse", "mvae", "ddpm5", "ddpm200", "ddgan", "aamdm")
"""The six panels of the figure (AAMDM Figure 3)."""
LABELS = {
    "mse": "MSE regressor",
    "mvae": "MVAE (CVAE)",
    "ddpm5": "DDPM-5",
    "ddpm200": "DDPM-200",
    "adm5": "ADM-5 (polisher alone)",
    "ddgan": "DD-GAN alone (3)",
    "aamdm": "AAMDM (3 + 2)",
}


@dataclass
class Squ9StudyConfig:
    """Data, network sizes and training budgets of the Squ-9 study."""

    n_train: int = 20_000
    """Training pairs (and sequences of ``window + 1`` points for the polisher)."""
    n_eval: int = 4000
    """Evaluation conditions, one sample each."""
    window: int = 4
    """h: the polisher's rollout length (Algorithm 1; the paper uses 10 on motion)."""
    seed: int = 0
    """Seeds data, weights and training."""
    width: int = 128
    """Hidden units of every network."""
    depth: int = 4
    """Layers of every network."""
    baseline_steps: int = 2000
    """Training steps of the MSE, MVAE and DDPM baselines (chapter 1's budget)."""
    baseline_lr: float = 3e-3
    """Their Adam learning rate (cosine-decayed)."""
    batch_size: int = 512
    """Their batch size."""
    mvae_latent: int = 4
    """Size of the MVAE latent z."""
    mvae_beta: float = 0.5
    """Weight of the MVAE's KL term per data dimension."""
    latent_dim: int = 8
    """Size of the GAN latent r."""
    fourier: int = 32
    """Random Fourier features in the generator and the discriminator."""
    gan: GANConfig = field(
        default_factory=lambda: GANConfig(
            steps=4000, batch_size=256, lr_g=2e-4, lr_d=4e-4, r1_gamma=0.3
        )
    )
    """DD-GAN training."""
    polish: PolishConfig = field(
        default_factory=lambda: PolishConfig(steps=1000, batch_size=128, lr=3e-3)
    )
    """Polisher training (also ADM-5's)."""


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class Squ9Study:
    """Train, sample, time and plot every method of the Squ-9 study (see the module docstring).

    ``models`` maps a method to its network, ``train_seconds`` to its training time; samples
    and rows are computed on ``x_eval`` (``config.n_eval`` conditions).
    """

    def __init__(self, config: Squ9StudyConfig | None = None, device: str = "cpu") -> None:
        self.config = c = config or Squ9StudyConfig()
        self.device = torch.device(device)
        self.squ9 = Squ9()
        g = torch.Generator().manual_seed(c.seed)
        self.x_prev, self.x_next = self.squ9.sample_pairs(c.n_train, g)
        self.sequences = self.squ9.sample_sequence(c.window + 1, c.n_train // c.window, g)
        self.x_eval, _ = self.squ9.sample_pairs(c.n_eval, torch.Generator().manual_seed(c.seed + 1))
        self.x_eval = self.x_eval.to(self.device)
        self.models: dict[str, nn.Module] = {}
        self.schedules: dict[str, NoiseSchedule] = {}
        self.train_seconds: dict[str, float] = {}
        self.discriminators: dict[str, DDGANDiscriminator] = {}
        self.generators: dict[int, nn.Module] = {}
        """Generators of the ablation by T_gan (3: the main model's)."""
        self.polishers: dict[int, nn.Module] = {}
        """Polishers of the ablation by T_adm (2: the main model's)."""

    # ---------------------------------------------------------------------------- training

    def _net_seed(self) -> None:
        torch.manual_seed(self.config.seed)

    def _gen(self) -> torch.Generator:
        return torch.Generator(self.device).manual_seed(self.config.seed)

    def _timed(self, name: str, fn) -> None:
        t0 = time.perf_counter()
        fn()
        self.train_seconds[name] = time.perf_counter() - t0

    def train(self, methods: tuple[str, ...] = METHODS, progress: bool = False) -> Squ9Study:
        """Train ``methods`` (AAMDM's modules once for ``ddgan`` and ``aamdm``)."""
        for m in methods:
            if m not in METHODS:
                raise ValueError(f"methods must be among {METHODS}, got {m!r}")
        for m in methods:
            if m in self.models or (m == "ddgan" and "aamdm" in self.models):
                continue
            if progress:
                print(f"training {m} ...", flush=True)
            getattr(self, f"_train_{m if m != 'ddgan' else 'aamdm'}")()
            if m == "ddgan":
                self.models["ddgan"] = self.models["aamdm"]
        return self

    def _train_mse(self) -> None:
        c = self.config
        self._net_seed()
        model = MLPRegressor(2, 2, c.width, c.depth).to(self.device)
        kw = dict(steps=c.baseline_steps, batch_size=c.batch_size, lr=c.baseline_lr)
        self._timed(
            "mse",
            lambda: train_regressor(model, self.x_prev, self.x_next, **kw, generator=self._gen()),
        )
        self.models["mse"] = model.eval()

    def _train_mvae(self) -> None:
        from minimdm.amdm.losses import frame_loss

        c = self.config
        self._net_seed()
        model = MVAE(MVAEConfig(2, 2, c.mvae_latent, c.width, c.depth)).to(self.device)
        xp, xn, g = self.x_prev.to(self.device), self.x_next.to(self.device), self._gen()
        opt = torch.optim.Adam(model.parameters(), lr=c.baseline_lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=c.baseline_steps)

        def fit() -> None:
            model.train()
            for _ in range(c.baseline_steps):
                idx = torch.randint(0, len(xn), (c.batch_size,), generator=g, device=self.device)
                loss, _ = frame_loss(model, xn[idx], xp[idx], g, "mvae", kl_beta=c.mvae_beta)
                optimizer_step(opt, loss.mean(), list(model.parameters()))
                sched.step()

        self._timed("mvae", fit)
        self.models["mvae"] = model.eval()

    def _train_ddpm(self, name: str, T: int) -> None:
        c = self.config
        self._net_seed()
        model = MLPDenoiser(DenoiserConfig(2, 2, c.width, c.depth, time_dim=32)).to(self.device)
        sched = NoiseSchedule("cosine", T, device=self.device)
        kw = dict(steps=c.baseline_steps, batch_size=c.batch_size, lr=c.baseline_lr)
        self._timed(
            name,
            lambda: train_denoiser(
                model, sched, self.x_prev, self.x_next, **kw, generator=self._gen()
            ),
        )
        self.models[name], self.schedules[name] = model.eval(), sched

    def _train_ddpm5(self) -> None:
        self._train_ddpm("ddpm5", 5)

    def _train_ddpm200(self) -> None:
        self._train_ddpm("ddpm200", 200)

    def _train_adm5(self) -> None:
        c = self.config
        self._net_seed()
        model = MLPDenoiser(DenoiserConfig(2, 2, c.width, c.depth, 32, "x0")).to(self.device)
        sched = aamdm_schedule(3, 2, self.device)
        self._timed("adm5", lambda: train_polisher(model, sched, self.sequences, sched.T, c.polish))
        self.models["adm5"], self.schedules["adm5"] = model.eval(), sched

    def data_range(self) -> tuple[Tensor, Tensor]:
        """The per-coordinate range of the training points: the AAMDM's x0 clamp."""
        return data_range([self.x_prev, self.x_next, self.sequences.reshape(-1, 2)])

    def build_aamdm(self, T_gan: int = 3, T_adm: int = 2) -> AAMDM:
        """An untrained AAMDM of this study's size (weights seeded by ``config.seed``)."""
        c = self.config
        self._net_seed()
        cfg = AAMDMConfig(
            2,
            2,
            T_gan,
            T_adm,
            latent_dim=c.latent_dim,
            width=c.width,
            depth=c.depth,
            time_dim=32,
            fourier=c.fourier,
            clip_x0=self.data_range(),
        )
        return AAMDM(cfg).to(self.device)

    def train_polisher(self, model: AAMDM) -> float:
        """Fit ``model.polisher`` on its levels; returns seconds."""
        t0 = time.perf_counter()
        sched = model.schedule()
        train_polisher(model.polisher, sched, self.sequences, model.T_adm, self.config.polish)
        return time.perf_counter() - t0

    def train_generator(
        self, model: AAMDM, gan: GANConfig | None = None, disc_activation: str = "leaky_relu"
    ) -> float:
        """Fit ``model.generator`` against a new discriminator on the pairs; returns seconds.

        ``gan`` overrides ``config.gan`` (e.g. ``pairs="paper"``, which diffuses the output of
        ``model.polisher``: train that first); ``disc_activation`` is the discriminator's.
        """
        c = self.config
        gan = gan or c.gan
        self._net_seed()
        disc_cfg = DiscriminatorConfig(
            2, 2, c.width, 3, 32, fourier=c.fourier, activation=disc_activation
        )
        disc = DDGANDiscriminator(disc_cfg).to(self.device)
        t0 = time.perf_counter()
        windows = pairs_to_windows(self.x_prev, self.x_next)
        train_ddgan(
            model.generator,
            disc,
            model.schedule(),
            windows,
            model.T_gan,
            gan,
            polisher=model.polisher,
        )
        self.discriminators[f"T_gan={model.T_gan}"] = disc
        return time.perf_counter() - t0

    def _train_aamdm(self) -> None:
        model = self.build_aamdm(3, 2)
        t_polish = self.train_polisher(model)
        t_gan = self.train_generator(model)
        self.models["aamdm"] = model.eval()
        self.train_seconds.update(aamdm=t_polish + t_gan, ddgan=t_gan, polisher=t_polish)

    # ---------------------------------------------------------------------------- sampling

    @torch.no_grad()
    def sample(
        self, method: str, cond: Tensor | None = None, generator: torch.Generator | None = None
    ) -> tuple[Tensor, int]:
        """One next point per condition (default ``x_eval``): ``(samples (N, 2), net calls)``."""
        cond = self.x_eval if cond is None else cond.to(self.device)
        model = self.models[method]
        if method == "mse":
            return model(cond), 1
        if method == "mvae":
            return model.sample(cond, generator), 1
        if method in ("ddpm5", "ddpm200", "adm5"):
            s = self.schedules[method]
            pred = "x0" if method == "adm5" else "eps"
            x = ddpm_sample(
                model, s, tuple(cond.shape), cond=cond, generator=generator, predicts=pred
            )
            return x, s.T
        count = StepCount()
        x = model.sample(cond, generator, T_adm=0 if method == "ddgan" else None, count=count)
        return x, count.network_calls

    def evaluate(
        self, methods: tuple[str, ...] | None = None, seed: int = 2, repeats: int = 5
    ) -> tuple[list[dict], dict[str, Tensor]]:
        """Metrics and timings of ``methods`` (default: every trained one), in table order.

        Each method samples ``x_eval`` ``repeats`` times from the same seed (``seed``); the
        fastest run is timed (the others absorb warm-up and noise from other processes).
        Returns the rows (one dict per method) and the samples.
        """
        methods = tuple(m for m in METHODS if m in self.models) if methods is None else methods
        samples, seconds, calls = {}, {}, {}
        for m in methods:
            best = float("inf")
            for _ in range(repeats):
                g = torch.Generator(self.device).manual_seed(seed)
                _sync(self.device)
                t0 = time.perf_counter()
                x, n = self.sample(m, generator=g)
                _sync(self.device)
                best = min(best, time.perf_counter() - t0)
            samples[m], seconds[m], calls[m] = x.cpu(), best, n
        ref = seconds.get("ddpm200")
        rows = []
        for m in methods:
            q = squ9_metrics(self.x_eval.cpu(), samples[m], self.squ9)
            rows.append(
                {
                    "method": m,
                    "label": LABELS[m],
                    "coverage": round(q["coverage"], 4),
                    "precision": round(q["precision"], 4),
                    "transition_tv": round(q["transition_tv"], 4),
                    "network_calls": calls[m],
                    "ms_per_step": round(1000 * seconds[m] / calls[m], 4),
                    "ms_per_batch": round(1000 * seconds[m], 3),
                    "speedup_vs_ddpm200": round(ref / seconds[m], 2) if ref else None,
                    "train_s": round(self.train_seconds.get(m, float("nan")), 2),
                }
            )
        return rows, samples

    # ---------------------------------------------------------------------------- ablations

    def ablation(
        self,
        T_gans: tuple[int, ...] = (2, 3, 4, 10),
        T_adms: tuple[int, ...] = (0, 1, 2, 3),
        seed: int = 2,
        rollout_chains: int = 128,
        rollout_steps: int = 100,
        progress: bool = False,
    ) -> tuple[list[dict], dict[tuple[int, int], Tensor]]:
        """AAMDM Table 2 on Squ-9: vary T_ADM with T_GAN = 3, and T_GAN with T_ADM = 2.

        Each setting is scored on one transition per evaluation condition and on an
        auto-regressive rollout (``rollout_chains`` chains of ``rollout_steps`` transitions,
        each sample the next condition), where polishing is meant to matter (§4.3). Returns one
        row per setting (``T_gan``, ``T_adm``, metrics, ``rollout_*`` metrics, ms per step,
        training seconds of what was retrained) and the one-step samples by ``(T_gan, T_adm)``.
        """
        self.train(("aamdm",))
        main = self.models["aamdm"]
        self.generators.setdefault(3, main.generator)
        self.polishers.setdefault(2, main.polisher)
        trained: dict[tuple[int, int], float] = {}
        for T_gan in T_gans:
            if T_gan not in self.generators:
                if progress:
                    print(f"training the generator for T_gan = {T_gan} ...", flush=True)
                m = self.build_aamdm(T_gan, 2)
                m.polisher.load_state_dict(main.polisher.state_dict())  # for pairs="paper"
                trained[(T_gan, 2)] = self.train_generator(m)
                self.generators[T_gan] = m.generator.eval()
        for T_adm in T_adms:
            if T_adm not in self.polishers and T_adm > 0:
                if progress:
                    print(f"training the polisher for T_adm = {T_adm} ...", flush=True)
                m = self.build_aamdm(3, T_adm)
                trained[(3, T_adm)] = self.train_polisher(m)
                self.polishers[T_adm] = m.polisher.eval()
        settings = [(3, a) for a in T_adms]
        settings += [(g, 2) for g in T_gans if not (g == 3 and 2 in T_adms)]
        start = self.squ9.sample_points(
            torch.arange(rollout_chains) % 9, torch.Generator().manual_seed(seed + 6)
        ).to(self.device)
        rows, samples = [], {}
        for T_gan, T_adm in settings:
            m = self.ablation_model(T_gan, T_adm)
            g = torch.Generator(self.device).manual_seed(seed)
            count = StepCount()
            _sync(self.device)
            t0 = time.perf_counter()
            with torch.no_grad():
                x = m.sample(self.x_eval, g, T_adm=T_adm, count=count)
            _sync(self.device)
            sec = time.perf_counter() - t0
            q = squ9_metrics(self.x_eval.cpu(), x.cpu(), self.squ9)
            with torch.no_grad():
                chain = autoregress(
                    lambda f, x, m=m, g=g, a=T_adm: m.sample(x, g, T_adm=a),
                    start,
                    rollout_steps,
                    desc="squ9 rollout",
                )
            ch = torch.cat([start.cpu()[:, None], chain], 1)  # (chains, steps + 1, 2)
            qr = squ9_metrics(ch[:, :-1].reshape(-1, 2), ch[:, 1:].reshape(-1, 2), self.squ9)
            samples[(T_gan, T_adm)] = x.cpu()
            rows.append(
                {
                    "T_gan": T_gan,
                    "T_adm": T_adm,
                    "coverage": round(q["coverage"], 4),
                    "precision": round(q["precision"], 4),
                    "transition_tv": round(q["transition_tv"], 4),
                    "rollout_precision": round(qr["precision"], 4),
                    "rollout_tv": round(qr["transition_tv"], 4),
                    "rollout_max_abs": round(ch.abs().max().item(), 2),
                    "network_calls": count.network_calls,
                    "ms_per_step": round(1000 * sec / count.network_calls, 4),
                    "retrained_s": round(trained.get((T_gan, T_adm), 0.0), 1),
                }
            )
        return rows, samples

    def ablation_model(self, T_gan: int, T_adm: int) -> AAMDM:
        """The (T_gan, T_adm) model of the ablation from the trained parts (T_adm = 0: a
        T_gan + 2 model, to be sampled with ``T_adm=0``)."""
        if T_gan not in self.generators or (T_adm > 0 and T_adm not in self.polishers):
            raise ValueError(
                f"no trained parts for T_gan = {T_gan}, T_adm = {T_adm}: generators for "
                f"{sorted(self.generators)}, polishers for {sorted(self.polishers)}; run ablation()"
            )
        m = self.build_aamdm(T_gan, T_adm if T_adm > 0 else 2)
        m.generator.load_state_dict(self.generators[T_gan].state_dict())
        if T_adm > 0:
            m.polisher.load_state_dict(self.polishers[T_adm].state_dict())
        return m.eval()

    # ---------------------------------------------------------------------------- storage

    def save(self, folder: str | Path) -> list[Path]:
        """Write every trained model as a checkpoint ``folder/NAME.safetensors`` (+ JSON)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        meta = {
            "study_config": asdict(self.config),
            "command": "python benchmarks/squ9_acceleration.py --ablation --save "
            + folder.as_posix(),
        }
        out = []
        for name, model in self.models.items():
            if name == "ddgan":
                continue  # the generation module of "aamdm"
            extra = {"method": name, "train_s": self.train_seconds.get(name)}
            if name in self.schedules and name != "adm5":
                extra["diffusion"] = {"schedule": "cosine", "T": self.schedules[name].T}
            out.append(save_checkpoint(folder / name, model, {**meta, **extra}).weights)
        for T_gan, gen in self.generators.items():
            if T_gan != 3:
                out.append(save_checkpoint(folder / f"generator_T{T_gan}", gen, meta).weights)
        for T_adm, pol in self.polishers.items():
            if T_adm != 2:
                out.append(save_checkpoint(folder / f"polisher_T{T_adm}", pol, meta).weights)
        return out

    @classmethod
    def load(cls, folder: str | Path, device: str = "cpu") -> Squ9Study:
        """The study saved by :meth:`save`, with the same data (its config's seed)."""
        folder = Path(folder)
        if not (folder / "aamdm.safetensors").exists():
            raise FileNotFoundError(f"no Squ-9 study in {folder}: expected aamdm.safetensors")
        cfg = load_checkpoint(folder / "aamdm").metadata["study_config"]
        cfg["gan"], cfg["polish"] = GANConfig(**cfg["gan"]), PolishConfig(**cfg["polish"])
        study = cls(Squ9StudyConfig(**cfg), device)
        for path in sorted(folder.glob("*.safetensors")):
            if path.name.endswith(".train.safetensors"):
                continue
            ck = load_checkpoint(path, device=device)
            name = path.name[: -len(".safetensors")]
            if name.startswith("generator_T"):
                study.generators[int(name[11:])] = ck.model
            elif name.startswith("polisher_T"):
                study.polishers[int(name[10:])] = ck.model
            else:
                study.models[name] = ck.model
                study.train_seconds[name] = ck.metadata.get("train_s") or float("nan")
                if name in ("ddpm5", "ddpm200"):
                    study.schedules[name] = ck.schedule(device)
                if name == "adm5":
                    study.schedules[name] = aamdm_schedule(3, 2, device)
        if "aamdm" in study.models:
            study.models["ddgan"] = study.models["aamdm"]
            study.generators.setdefault(3, study.models["aamdm"].generator)
            study.polishers.setdefault(2, study.models["aamdm"].polisher)
        return study


def with_budget(config: Squ9StudyConfig, scale: float) -> Squ9StudyConfig:
    """``config`` with every training budget multiplied by ``scale`` (quick runs, notebooks)."""
    return replace(
        config,
        baseline_steps=max(1, int(config.baseline_steps * scale)),
        gan=replace(config.gan, steps=max(1, int(config.gan.steps * scale))),
        polish=replace(config.polish, steps=max(1, int(config.polish.steps * scale))),
    )
