"""Training loop, scheduled sampling and checkpoints on tiny configs with synthetic features."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as hst
from torch import nn

from minimdm import files
from minimdm.amdm.losses import make_windows, window_loss
from minimdm.amdm.models import DenoiserConfig, MLPDenoiser, MLPRegressor
from minimdm.amdm.train import LOCOMOTION, train_amdm, window_weights
from minimdm.amdm.train_config import (
    TrainConfig,
    build_network,
    load_config,
    motion_mask,
    student_probability,
)
from minimdm.checkpoint import (
    CheckpointMismatchError,
    load_checkpoint,
    load_train_state,
    save_checkpoint,
)
from minimdm.diffusion import NoiseSchedule, predict_x0_from_eps
from minimdm.motion.features import FeatureLayout
from minimdm.motion.skeleton import Skeleton
from minimdm.nn import cosine_lr
from minimdm.validate import InputError

ROOT = Path(__file__).resolve().parents[1]
D = 8


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def synthetic_features(n_clips: int = 3, frames: int = 120, seed: int = 0) -> list[np.ndarray]:
    """Smooth multi-sine clips, roughly unit scale, like normalized motion features."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None]
    return [
        np.sin(t * rng.uniform(0.05, 0.3, size=(1, D)) + rng.uniform(0, 6, size=(1, D))).astype(
            np.float32
        )
        for _ in range(n_clips)
    ]


def tiny(**kw) -> TrainConfig:
    base = dict(
        width=32,
        depth=3,
        time_dim=16,
        T=8,
        batch_size=16,
        total_steps=6,
        rollout=3,
        teacher_steps=2,
        ramp_steps=2,
        eval_interval=0,
        ckpt_interval=0,
        log_interval=1,
        eval_windows=32,
        lr=1e-3,
    )
    base.update(kw)
    return TrainConfig(**base)


def test_loss_falls_on_a_tiny_config(tmp_path):
    cfg = tiny(total_steps=150, teacher_steps=50, ramp_steps=50, eval_interval=150, log_interval=10)
    result = train_amdm(cfg, tmp_path, synthetic_features(), progress=False)
    losses = [h["loss"] for h in result.history if "loss" in h]
    assert result.steps == 150
    assert np.mean(losses[-3:]) < 0.7 * losses[0]
    assert result.history[-1]["eval_loss"] < losses[0]
    assert (tmp_path / "model.safetensors").exists() and (tmp_path / "log.jsonl").exists()


def test_mvae_weights_carry_the_names_of_its_encoder_and_decoder_mlp(tmp_path):
    """Training writes, and every shipped MVAE holds, the MVAE's own names: ``encoder.*`` (an
    nn.Sequential) and ``decoder.*`` (an MLP: input, hidden.i, norms.i, output), nothing else."""
    from safetensors import safe_open

    from minimdm.nn import MLP

    def names(c: dict) -> set[str]:
        x, cond, z, w = c["x_dim"], c["cond_dim"], c["latent_dim"], c["width"]
        enc = MLP(x + cond, 2 * z, w, depth=3).sequential().state_dict()
        dec = MLP(cond, x, w, c["depth"], concat_dim=z).state_dict()
        return {f"encoder.{k}" for k in enc} | {f"decoder.{k}" for k in dec}

    cfg = tiny(model_kind="mvae", latent_dim=4, total_steps=2, ckpt_interval=2)
    train_amdm(cfg, tmp_path, synthetic_features(), progress=False)
    want = names(dict(x_dim=D, cond_dim=D, latent_dim=4, width=cfg.width, depth=cfg.depth))
    assert set(load_checkpoint(tmp_path).model.state_dict()) == want
    with safe_open(str(tmp_path / "model.safetensors"), "pt") as f:
        assert set(f.keys()) == want
    _, state = load_train_state(tmp_path)
    assert set(state["model"]) == set(state["ema"]) == want
    metas = {p: json.loads(p.read_text()) for p in (ROOT / "checkpoints").rglob("*.json")}
    shipped = [p for p, m in metas.items() if m.get("model", {}).get("kind") == "mvae"]
    assert len(shipped) >= 3
    for p in shipped:
        with safe_open(str(p.with_suffix(".safetensors")), "pt") as f:
            assert set(f.keys()) == names(metas[p]["model"]["config"]), p


class Interrupt(Exception):
    pass


@pytest.mark.parametrize("kind", ["amdm", "mse", "mvae"])
def test_resume_gives_the_same_next_step(tmp_path, kind):
    """k + 1 uninterrupted steps == k steps, a crash, a resume, and 1 more step (bit for bit)."""
    k = 5
    cfg = tiny(model_kind=kind, total_steps=k + 1, ckpt_interval=k)
    feats = synthetic_features()
    train_amdm(cfg, tmp_path / "full", feats, progress=False)

    def crash(step, record):
        if step == k:
            raise Interrupt

    with pytest.raises(Interrupt):
        train_amdm(cfg, tmp_path / "cut", feats, progress=False, callback=crash)
    assert load_train_state(tmp_path / "cut")[1]["step"] == k
    resumed = train_amdm(cfg, tmp_path / "cut", feats, progress=False)
    assert resumed.steps == k + 1
    _, a = load_train_state(tmp_path / "full")
    _, b = load_train_state(tmp_path / "cut")
    for name in ("model", "ema"):
        for key in a[name]:
            assert torch.equal(a[name][key], b[name][key]), (name, key)
    for pid, st in a["optimizer"]["state"].items():
        for key, v in st.items():
            assert torch.equal(v, b["optimizer"]["state"][pid][key])
    assert torch.equal(a["generator"], b["generator"])
    # the log of the resumed run has each step once
    steps = [r["step"] for r in resumed.history if "loss" in r]
    assert steps == [k + 1]
    # the checkpoint records both calls as segments: steps 0..k, then k..k+1
    segs = load_checkpoint(tmp_path / "cut").metadata["segments"]
    assert [(g["from_step"], g["to_step"]) for g in segs] == [(0, k), (k, k + 1)]
    assert all(g["seconds"] >= 0 and g["threads"] >= 1 for g in segs)
    full = load_checkpoint(tmp_path / "full").metadata["segments"]
    assert [(g["from_step"], g["to_step"]) for g in full] == [(0, k + 1)]
    # a resumed run with another model config is refused, naming the difference
    with pytest.raises(ValueError, match="width"):
        train_amdm(tiny(model_kind=kind, width=48, total_steps=k + 2), tmp_path / "cut", feats)


@given(
    hst.lists(
        hst.tuples(hst.integers(0, 40), hst.sampled_from([*LOCOMOTION, "bow", "dance", None])),
        min_size=1,
        max_size=12,
    ),
    hst.floats(0.05, 1.0),
    hst.sampled_from(["equal", "frames"]),
)
def test_window_weights_give_locomotion_its_share_split_by_content(clips, share, split):
    n = 3
    lengths, contents = [f for f, _ in clips], [c for _, c in clips]
    w = window_weights(lengths, n, contents, share, split)
    counts = [max(0, f - n) for f in lengths]
    assert w.shape == (sum(counts),) and (w >= 0).all()
    if not w.numel():
        return
    assert float(w.sum()) == pytest.approx(1.0)
    label = [c for c, k in zip(contents, counts, strict=True) for _ in range(k)]
    by_content = {}
    for c, wi in zip(label, w.tolist(), strict=True):
        by_content[c] = by_content.get(c, 0.0) + wi
    loco = [c for c in by_content if c in LOCOMOTION]
    rest = [c for c in by_content if c not in LOCOMOTION]
    if loco and rest:
        assert sum(by_content[c] for c in loco) == pytest.approx(share)
    if split == "equal":  # equal among the locomotion contents present
        for c in loco:
            assert by_content[c] == pytest.approx(by_content[loco[0]])
    else:  # every locomotion window alike, so a content counts by its windows
        moving = [wi for c, wi in zip(label, w.tolist(), strict=True) if c in LOCOMOTION]
        assert max(moving, default=0) == pytest.approx(min(moving, default=0))
    others = [wi for c, wi in zip(label, w.tolist(), strict=True) if c not in LOCOMOTION]
    assert max(others, default=0) == pytest.approx(min(others, default=0))  # by count
    with pytest.raises(ValueError, match="split"):
        window_weights(lengths, n, contents, share, "by-speed")


def test_locomotion_share_needs_content_labels(tmp_path):
    with pytest.raises(InputError, match="content labels"):
        train_amdm(tiny(locomotion_share=0.8), tmp_path, synthetic_features(), progress=False)
    with pytest.raises(ValueError, match="locomotion_share"):
        tiny(locomotion_share=1.5)
    with pytest.raises(ValueError, match="locomotion_split"):
        tiny(locomotion_split="speed")


def test_half_storage_keeps_full_precision_for_resume(tmp_path):
    """``storage: float16`` halves the sampling weights, which load back as float32 within
    fp16 rounding; the training state stays float32, so a run resumed from it (here with the
    storage switched back) matches the uninterrupted float32 run bit for bit."""
    k = 4
    feats = synthetic_features()
    train_amdm(tiny(total_steps=k + 1), tmp_path / "full", feats, progress=False)

    def crash(step, record):
        if step == k:
            raise Interrupt

    cfg = tiny(total_steps=k + 1, ckpt_interval=k, storage="float16")
    with pytest.raises(Interrupt):
        train_amdm(cfg, tmp_path / "half", feats, progress=False, callback=crash)
    half = load_checkpoint(tmp_path / "half")
    assert half.metadata["storage"] == "float16"

    def tensor_bytes(path):  # a safetensors file: 8 bytes of header length, header, tensors
        with open(path, "rb") as f:
            header = int.from_bytes(f.read(8), "little")
        return path.stat().st_size - 8 - header  # the header (config and metadata) left out

    stored = tensor_bytes(tmp_path / "half" / "model.safetensors")
    _, state = load_train_state(tmp_path / "half")
    for key, value in half.model.state_dict().items():
        exact = state["ema"][key]
        assert value.dtype == torch.float32 and exact.dtype == torch.float32
        assert torch.allclose(value, exact, rtol=1e-3, atol=1e-4), key
    train_amdm(tiny(total_steps=k + 1, ckpt_interval=k), tmp_path / "half", feats, progress=False)
    _, a = load_train_state(tmp_path / "full")
    _, b = load_train_state(tmp_path / "half")
    for key in a["model"]:
        assert torch.equal(a["model"][key], b["model"][key]), key
    full_size = tensor_bytes(tmp_path / "half" / "model.safetensors")
    assert stored == full_size // 2  # the float32 save after the resume is twice as big
    with pytest.raises(ValueError, match="storage"):
        tiny(storage="float8")


def test_the_loop_averages_with_the_shared_ema_and_follows_the_shared_schedule(tmp_path):
    """One step from the seeded initial weights: the EMA is ``ema_update`` of them (d = 0.1 at
    step 0), and every step's learning rate is ``cosine_lr`` of the config."""
    cfg = tiny(total_steps=1, ema_decay=0.99, lr=1e-3, lr_min=1e-4)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        init = build_network(cfg, D).state_dict()
    train_amdm(cfg, tmp_path, synthetic_features(), progress=False)
    _, state = load_train_state(tmp_path)
    for key, theta in state["model"].items():
        assert not torch.equal(theta, init[key]) or key.startswith("norms")  # it moved
        assert torch.equal(state["ema"][key], init[key].lerp(theta, 1 - 0.1)), key
    rates = []
    cfg = tiny(total_steps=7, lr=1e-3, lr_min=1e-4, ema_decay=0.0)
    train_amdm(cfg, tmp_path / "lr", synthetic_features(), progress=False,
               callback=lambda step, rec: rates.append(rec["lr"]))  # fmt: skip
    assert rates == [cosine_lr(s, 7, 1e-3, 1e-4) for s in range(7)]
    assert rates[0] == 1e-3 and rates[-1] == pytest.approx(1e-4)


def test_student_probability_schedule():
    cfg = tiny(teacher_steps=100, ramp_steps=50)
    assert [student_probability(cfg, s) for s in (0, 50, 99)] == [0.0, 0.0, 0.0]
    assert 0.0 < student_probability(cfg, 110) < 1.0
    assert student_probability(cfg, 124) == pytest.approx(0.5)
    assert student_probability(cfg, 149) == 1.0
    assert student_probability(cfg, 10_000) == 1.0
    assert student_probability(tiny(teacher_steps=3, ramp_steps=0), 3) == 1.0


class SpyRegressor(MLPRegressor):
    """Records every condition it is given and every prediction it makes."""

    def __init__(self):
        super().__init__(D, D, width=16, depth=2)
        self.conds, self.outs = [], []

    def forward(self, cond):
        out = super().forward(cond)
        self.conds.append(cond.detach().clone())
        self.outs.append(out.detach().clone())
        return out


class SpyDenoiser(MLPDenoiser):
    def __init__(self, predicts="eps"):
        super().__init__(DenoiserConfig(D, D, width=16, depth=2, time_dim=8, predicts=predicts))
        self.calls = []

    def forward(self, x_t, t, cond=None):
        out = super().forward(x_t, t, cond)
        self.calls.append((x_t.detach().clone(), t.clone(), cond.detach().clone(), out.detach()))
        return out


def test_student_forcing_feeds_the_models_own_prediction():
    windows = make_windows(synthetic_features(), 3)[:32]  # (32, 4, D)
    g = torch.Generator().manual_seed(0)
    spy = SpyRegressor()
    window_loss(spy, windows, 1.0, g, kind="mse")
    assert len(spy.conds) == 3
    assert torch.equal(spy.conds[0], windows[:, 0])
    assert torch.equal(spy.conds[1], spy.outs[0])  # frame 2 is conditioned on prediction 1
    assert torch.equal(spy.conds[2], spy.outs[1])
    assert not torch.allclose(spy.conds[1], windows[:, 1])

    spy = SpyRegressor()
    window_loss(spy, windows, 0.0, g, kind="mse")  # teacher forcing: one batch of GT frames
    assert len(spy.conds) == 1
    assert torch.equal(spy.conds[0], windows[:, :-1].reshape(-1, D))

    # A-MDM: the next condition is x0_hat at the drawn noise level, clamped
    sched = NoiseSchedule("cosine", 8)
    spy = SpyDenoiser()
    window_loss(spy, windows, 1.0, g, kind="amdm", schedule=sched, clip_x0=2.0)
    x_t, t, _, eps = spy.calls[0]
    x0_hat = predict_x0_from_eps(sched, x_t, t, eps).clamp(-2, 2)
    assert torch.allclose(spy.calls[1][2], x0_hat, atol=1e-6)

    # an intermediate probability mixes the two per sample
    spy = SpyRegressor()
    big = make_windows(synthetic_features(frames=400), 2)[:1000]
    _, info = window_loss(spy, big, 0.3, g, kind="mse")
    from_model = (spy.conds[1] == spy.outs[0]).all(1).float().mean()
    assert 0.25 < float(from_model) < 0.35
    assert info["student_frac"] == pytest.approx(float(from_model))


def test_teacher_weight_adds_the_teacher_forced_loss_to_student_forcing():
    windows = make_windows(synthetic_features(), 3)[:32]  # (32, 4, D)
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    spy = SpyRegressor()
    student, _ = window_loss(spy, windows, 1.0, g, kind="mse")
    teacher, _ = window_loss(spy, windows, 0.0, g, kind="mse")
    n = len(spy.conds)
    both, _ = window_loss(spy, windows, 1.0, g, kind="mse", teacher_weight=0.5)
    assert float(both) == pytest.approx(float(student) + 0.5 * float(teacher), rel=1e-6)
    # the added term is one batch of every frame from its ground-truth predecessor
    assert len(spy.conds) == n + 3 + 1
    assert torch.equal(spy.conds[-1], windows[:, :-1].reshape(-1, D))
    # pure teacher forcing is unchanged by it, and a negative weight is refused
    again, _ = window_loss(spy, windows, 0.0, g, kind="mse", teacher_weight=0.5)
    assert float(again) == pytest.approx(float(teacher))
    with pytest.raises(ValueError, match="teacher_weight"):
        window_loss(spy, windows, 1.0, g, kind="mse", teacher_weight=-1.0)
    with pytest.raises(ValueError, match="teacher_weight must be a finite float >= 0"):
        TrainConfig(teacher_weight=float("nan"))


def small_model():
    torch.manual_seed(0)
    return MLPDenoiser(DenoiserConfig(D, D, width=16, depth=3, time_dim=8))


def skel(n: int = 3, names=None) -> Skeleton:
    names = names or [f"j{i}" for i in range(n)]
    return Skeleton(
        names, [-1] + list(range(n - 1)), np.ones((n, 3)) * 0.1, foot_joints=[names[-1]]
    )


def test_checkpoint_round_trip_without_pickle(tmp_path, monkeypatch):
    m = small_model()
    layout = {"dim": D, "slices": {"root": [0, 3], "pos": [3, 8]}}
    meta = {"step": 7, "feature_layout": layout, "skeleton": skel(), "normalizer": {"mean": [0.0]}}
    opt = torch.optim.Adam(m.parameters())
    m(torch.randn(2, D), torch.zeros(2, dtype=torch.long), torch.randn(2, D)).sum().backward()
    opt.step()
    state = {"optimizer": opt.state_dict(), "gen": torch.Generator().manual_seed(3).get_state()}
    save_checkpoint(tmp_path / "ck", m, meta, optimizer_state=state)

    def no_torch_load(*a, **k):
        raise AssertionError("torch.load must not be used")

    monkeypatch.setattr(torch, "load", no_torch_load)
    ck = load_checkpoint(
        tmp_path / "ck.safetensors", expected_layout=layout, expected_skeleton=skel()
    )
    assert ck.kind == "amdm" and ck.step == 7
    assert ck.metadata["minimdm_version"]
    for k, v in m.state_dict().items():
        assert torch.equal(ck.model.state_dict()[k], v)
    _, st = load_train_state(tmp_path / "ck")
    opt2 = torch.optim.Adam(small_model().parameters())
    opt2.load_state_dict(st["optimizer"])  # int keys and tuples (betas) survive JSON
    assert opt2.state_dict()["param_groups"][0]["betas"] == (0.9, 0.999)
    assert torch.equal(st["gen"], state["gen"])


def test_checkpoint_mismatch_names_both(tmp_path):
    m = small_model()
    layout = FeatureLayout(("j0", "j1", "j2"))
    save_checkpoint(tmp_path, m, {"feature_layout": layout, "skeleton": skel(3)})
    with pytest.raises(CheckpointMismatchError) as e:
        load_checkpoint(tmp_path, expected_layout=FeatureLayout(("j0", "j1")))
    msg = str(e.value)
    assert "feature layout" in msg and '"dim":39' in msg and '"dim":27' in msg
    other = skel(3, names=["hips", "knee", "toe"])
    with pytest.raises(CheckpointMismatchError) as e:
        load_checkpoint(tmp_path, expected_skeleton=other)
    msg = str(e.value)
    assert "skeleton" in msg and '"j0"' in msg and '"hips"' in msg
    load_checkpoint(tmp_path, expected_layout=layout, expected_skeleton=skel(3))  # match: fine


def test_interrupted_save_keeps_the_last_good_checkpoint(tmp_path, monkeypatch):
    good = small_model()
    save_checkpoint(tmp_path, good, {"step": 1}, optimizer_state={"step": 1})
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def crash_mid_write(f, data):
        f.write(data[: len(data) // 2])
        raise OSError("disk full")

    monkeypatch.setattr(files, "_write", crash_mid_write)
    newer = MLPDenoiser(DenoiserConfig(D, D, width=16, depth=3, time_dim=8))
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(tmp_path, newer, {"step": 2}, optimizer_state={"step": 2})
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert after == before  # nothing changed, no temporary files left
    ck = load_checkpoint(tmp_path)
    assert ck.step == 1
    for k, v in good.state_dict().items():
        assert torch.equal(ck.model.state_dict()[k], v)


def test_configs_load_and_build(tmp_path):
    # aamdm_*.yaml are AAMDM's own configs (tests/test_aamdm.py loads them), rl_*.yaml the
    # steering policies' and camdm*.yaml CAMDM's (tests/test_config.py).
    own = ("aamdm", "rl_", "camdm")
    files = sorted(f for f in (ROOT / "configs").glob("*.yaml") if not f.name.startswith(own))
    assert {"amdm.yaml", "amdm_paper.yaml", "mse.yaml", "mvae.yaml"} <= {f.name for f in files}
    for f in files:
        cfg = load_config(f)
        assert cfg.config_file.endswith(f.name)
        scale = [0.1] * 183 if cfg.delta else None  # a delta model's spread of change (k)
        net = build_network(cfg, 183, delta_scale=scale)
        assert isinstance(net, nn.Module)
        assert getattr(net, "is_delta", False) == cfg.delta, f.name
    paper = load_config(ROOT / "configs" / "amdm_paper.yaml")
    assert (paper.width, paper.depth, paper.T) == (1024, 10, 40)
    bad = tmp_path / "bad.yaml"
    bad.write_text("width: 64\nwidht: 3\n")
    with pytest.raises(ValueError, match="widht"):
        load_config(bad)
    odd = tmp_path / "odd.yaml"
    odd.write_text("lr: 5e-4\nfps: 30\n")  # YAML 1.1 reads 5e-4 as a string
    cfg = load_config(odd)
    assert cfg.lr == 5e-4 and isinstance(cfg.fps, float)
    odd.write_text("width: wide\n")
    with pytest.raises(ValueError, match="width must be int, got 'wide'"):
        load_config(odd)


def test_student_steps_feed_back_a_draw_of_the_reverse_chain():
    windows = make_windows(synthetic_features(), 3)[:16]  # (16, 4, D)
    sched = NoiseSchedule("cosine", 8)
    for k, calls in ((8, 8), (3, 3)):  # DDPM over all T steps, or DDIM over k
        spy = SpyDenoiser("x0")
        window_loss(spy, windows, 1.0, torch.Generator().manual_seed(0), schedule=sched,
                    predicts="x0", student_steps=k)  # fmt: skip
        # per frame: one loss call; before frames 2 and 3, a chain of `calls` steps
        assert len(spy.calls) == 3 + 2 * calls
        chain = spy.calls[1 : 1 + calls]
        assert [int(c[1][0]) for c in chain][0] == 7  # the chain starts at the noisiest level
        assert all(torch.equal(c[2], windows[:, 0]) for c in chain)  # from the same condition
        # the next frame is conditioned on the chain's last clean estimate
        assert torch.allclose(spy.calls[1 + calls][2], chain[-1][3], atol=1e-6)
    spy = SpyDenoiser("x0")  # teacher forcing draws nothing
    window_loss(spy, windows, 0.0, torch.Generator().manual_seed(0), schedule=sched,
                predicts="x0", student_steps=8)  # fmt: skip
    assert len(spy.calls) == 1
    with pytest.raises(ValueError, match="student_steps must be >= 0"):
        TrainConfig(student_steps=-1)


def test_frame_geometry_is_zero_on_recorded_frames_and_sees_a_sliding_foot():
    from minimdm.amdm.losses import FrameGeometry
    from minimdm.motion.corpora import load_corpus
    from minimdm.motion.features import Normalizer, encode

    take = load_corpus("bandai-namco-1", split="test", takes=["dataset-1_walk_normal_001"])[0]
    feats = encode(take)  # (F, D)
    norm = Normalizer.fit([feats])
    x = norm.normalize(feats)
    J, feet = len(take.skeleton), take.skeleton.foot_indices
    from minimdm.motion.metrics import foot_contact_offsets

    offset = foot_contact_offsets(take.positions, feet)
    geo = FrameGeometry(norm.mean, norm.std, J, feet, offset, consistency=1, contact=0)
    one = torch.ones(x.shape[0] - 1)
    assert float(geo(x[1:], x[:-1], x[1:], one).max()) < 1e-8  # the parts of a frame agree
    # the displacement it implies is the recorded one, whole body
    disp = geo.displacement(x[1:], x[:-1])
    torch.testing.assert_close(disp, feats[1:, 3 + 3 * J : 3 + 6 * J].unflatten(-1, (J, 3)),
                               atol=1e-5, rtol=0)  # fmt: skip
    # move the root on without moving the body: the feet slide, both losses see it
    slid = feats.clone()
    slid[:, 0] += 0.02  # 2 cm a frame more forward speed
    xs = norm.normalize(slid)
    assert float(geo(xs[1:], x[:-1], x[1:], one).mean()) > 0.05
    contact = FrameGeometry(norm.mean, norm.std, J, feet, offset, consistency=0, contact=1)
    own = float(contact(x[1:], x[:-1], x[1:], one).mean())
    assert float(contact(xs[1:], x[:-1], x[1:], one).mean()) > 1.4 * own
    # the weight (alpha-bar of the drawn level) scales it, per sample
    assert float(contact(xs[1:], x[:-1], x[1:], 0 * one).abs().max()) == 0.0


def test_frame_geometry_bone_loss_measures_the_recorded_bones_and_a_stretched_one():
    from minimdm.amdm.losses import FrameGeometry
    from minimdm.motion import metrics
    from minimdm.motion.corpora import load_corpus
    from minimdm.motion.features import Normalizer, encode

    take = load_corpus("bandai-namco-1", split="test", takes=["dataset-1_walk_normal_001"])[0]
    feats = encode(take)  # (F, D)
    norm = Normalizer.fit([feats])
    x = norm.normalize(feats)
    sk = take.skeleton
    J, feet = len(sk), sk.foot_indices
    offset = metrics.foot_contact_offsets(take.positions, feet)
    geo = FrameGeometry(norm.mean, norm.std, J, feet, offset, 0.025, 0, 0, sk.parents, bones=1)
    # the bones of a frame's root-relative positions are the recording's bones
    recorded = metrics.bone_lengths(take.positions[1:], sk.parents).float()  # encode drops frame 0
    torch.testing.assert_close(geo.bone_lengths(x), recorded, atol=1e-4, rtol=0)
    one = torch.ones(x.shape[0] - 1)
    assert float(geo(x[1:], x[:-1], x[1:], one).abs().max()) < 1e-6
    # stretch one bone by 2 cm (the left hand, a leaf, along its bone): (2 cm / 1 cm)^2 / 20 bones
    hand = sk.names.index("Hand_L")
    pos = feats[:, 3 : 3 + 3 * J].unflatten(-1, (J, 3))
    along = pos[:, hand] - pos[:, sk.parents[hand]]
    stretched = feats.clone()
    k = 3 + 3 * hand
    stretched[:, k : k + 3] += 0.02 * along / along.norm(dim=-1, keepdim=True)
    loss = geo(norm.normalize(stretched)[1:], x[:-1], x[1:], one)
    torch.testing.assert_close(loss, torch.full_like(loss, 4 / (J - 1)), atol=2e-3, rtol=0)
    with pytest.raises(ValueError, match="parents"):
        FrameGeometry(norm.mean, norm.std, J, feet, offset, bones=1)


def test_feature_scale_standardises_every_varying_feature_to_that_spread():
    """feature_scale k divides the normalizer's std (and its floor) by k: the training frames come
    out k times as large, with std k where a feature varies, and the stored normalizer maps them
    back to the recorded features."""
    from minimdm.amdm.train import _load_data
    from minimdm.motion.features import Normalizer

    base = dict(corpus="bandai-namco-1", split="train", loop_frames=None,
                clips=["dataset-1_walk_normal_002", "dataset-1_run_normal_001"])  # fmt: skip
    one, four = _load_data(TrainConfig(**base)), _load_data(TrainConfig(**base, feature_scale=4.0))
    x1, x4 = torch.cat(one["features"]), torch.cat(four["features"])
    torch.testing.assert_close(x4, 4 * x1, rtol=1e-5, atol=1e-5)
    varying = one["normalizer"].std > one["normalizer"].floor
    assert int(varying.sum()) > 200
    std = x4.std(0, unbiased=False)[varying]
    torch.testing.assert_close(std, torch.full_like(std, 4.0))
    back = Normalizer.from_dict(four["normalizer"].to_dict()).denormalize(x4)
    torch.testing.assert_close(back, one["normalizer"].denormalize(x1), rtol=1e-5, atol=1e-4)
    with pytest.raises(ValueError, match="feature_scale must be a finite float > 0"):
        TrainConfig(feature_scale=0.0)


@settings(deadline=None)  # the first example builds two networks
@given(hst.integers(1, 6), hst.integers(0, 2**31 - 1))
def test_a_delta_model_maps_a_frame_to_its_change_and_back(batch, seed):
    """to_delta and from_delta are inverse; a model without delta_scale passes frames through."""
    g = torch.Generator().manual_seed(seed)
    k = torch.rand(D, generator=g) + 0.05
    net = MLPDenoiser(DenoiserConfig(D, D, 8, 2, 8, "x0", delta_scale=k.tolist()))
    plain = MLPDenoiser(DenoiserConfig(D, D, 8, 2, 8, "x0"))
    x, cond = torch.randn(batch, D, generator=g), torch.randn(batch, D, generator=g)
    z = net.to_delta(x, cond)
    torch.testing.assert_close(z, (x - cond) / k)
    torch.testing.assert_close(net.from_delta(z, cond), x)
    assert net.is_delta and not plain.is_delta
    root = MLPDenoiser(
        DenoiserConfig(
            D, D, 8, 2, 8, "x0", delta_scale=k.tolist(), delta_mask=[1.0] * 3 + [0.0] * (D - 3)
        )
    )
    z = root.to_delta(x, cond)  # the root's three features as a change, the joints as they are
    torch.testing.assert_close(z[:, :3], (x - cond)[:, :3] / k[:3])
    assert torch.equal(z[:, 3:], x[:, 3:])
    torch.testing.assert_close(root.from_delta(z, cond), x)
    assert torch.equal(root.delta_spread, k)  # cond_noise's unit, every feature's own change
    cfg = TrainConfig(delta=True, delta_features="root", T=6, width=8, depth=2)
    assert build_network(cfg, D, k.tolist()).delta_m.tolist() == [1.0] * 3 + [0.0] * (D - 3)
    layout = FeatureLayout(("hips", "foot"))  # 'not_positions': all but the joint positions
    cfg = TrainConfig(delta=True, delta_features="not_positions", T=6, width=8, depth=2)
    m = build_network(cfg, layout.dim, [0.5] * layout.dim).delta_m
    assert m[layout.joint_pos].eq(0).all() and m.sum() == layout.dim - 3 * layout.n_joints
    cfg = TrainConfig(delta=True, delta_features="joint_motion", T=6, width=8, depth=2)
    m = build_network(cfg, layout.dim, [0.5] * layout.dim).delta_m  # j_v and j_o only
    assert m[:3].eq(0).all() and m[layout.joint_pos].eq(0).all()
    assert m[layout.joint_vel].eq(1).all() and m[layout.joint_rot].eq(1).all()
    cfg = TrainConfig(delta=True, delta_features="rotations", T=6, width=8, depth=2)
    m = build_network(cfg, layout.dim, [0.5] * layout.dim).delta_m  # j_o only
    assert m[layout.joint_rot].eq(1).all() and m.sum() == 6 * layout.n_joints
    assert torch.equal(plain.to_delta(x, cond), x) and torch.equal(plain.from_delta(x, cond), x)


def test_a_delta_model_trains_on_the_change_and_samples_frames_inside_the_data_box(tmp_path):
    """The checkpoint records each feature's spread of the change between frames; a perfect
    x0-network of the change reconstructs the frame; sampled frames respect the frame clamp."""
    from minimdm.amdm.losses import frame_loss
    from minimdm.amdm.sampling import Sampler
    from minimdm.amdm.train_config import delta_scale

    feats = synthetic_features()
    cfg = tiny(delta=True, predicts="x0", total_steps=4)
    ckpt = train_amdm(cfg, tmp_path, feats, progress=False).checkpoint
    windows = make_windows([torch.as_tensor(a) for a in feats], cfg.rollout)
    k = torch.tensor(delta_scale(windows))
    change = torch.cat([torch.as_tensor(a[1:] - a[:-1]) for a in feats])
    assert k.shape == (D,) and (k > 0).all()
    assert (k / change.std(0)).sub(1).abs().max() < 0.1  # the spread of the frame-to-frame change
    net = ckpt.model
    torch.testing.assert_close(net.delta_k, k)

    class Oracle(nn.Module):  # returns the true clean change: the loss is 0, the prediction x
        def __init__(self):
            super().__init__()
            self.is_delta, self.to_delta, self.from_delta = True, net.to_delta, net.from_delta

        def forward(self, x_t, t, cond):
            return self.z

    oracle = Oracle()
    x, cond = windows[:16, 1], windows[:16, 0]
    oracle.z = net.to_delta(x, cond)
    sched = NoiseSchedule("cosine", cfg.T)
    loss, pred = frame_loss(oracle, x, cond, torch.Generator().manual_seed(0), "amdm", sched, "x0")
    assert loss.abs().max() < 1e-10
    torch.testing.assert_close(pred, x)

    sampler = Sampler.load(ckpt)
    lo, hi = (torch.as_tensor(b) for b in ckpt.diffusion["clip_x0"])
    frame = sampler.frame(cond, torch.Generator().manual_seed(1))
    assert frame.shape == cond.shape and ((frame >= lo) & (frame <= hi)).all()
    with pytest.raises(ValueError, match="delta_features must be one of"):
        tiny(delta=True, delta_features="joints")
    with pytest.raises(ValueError, match="delta needs model_kind: amdm"):
        tiny(model_kind="mse", delta=True)


def test_cond_noise_perturbs_only_the_condition_the_denoiser_sees():
    """The network sees x_{f-1} plus noise of the given spread; the target stays the frame."""
    from minimdm.amdm.losses import frame_loss

    seen = []

    class Recorder(nn.Module):
        def forward(self, x_t, t, cond):
            seen.append(cond.clone())
            return torch.zeros_like(x_t)

    x, cond = torch.randn(4096, D), torch.randn(4096, D)
    sched = NoiseSchedule("cosine", 8)
    for spread in (0.0, 0.3):
        g = torch.Generator().manual_seed(0)
        loss, pred = frame_loss(Recorder(), x, cond, g, "amdm", sched, "x0", cond_noise=spread)
        torch.testing.assert_close(loss, (x**2).mean(1))  # the target is x itself
        assert abs(float((seen[-1] - cond).std()) - spread) < 0.01
    delta = Recorder()  # a delta model's noise is in units of each feature's change k
    delta.is_delta, delta.delta_k = True, torch.linspace(0.05, 0.5, D)
    delta.delta_spread = delta.delta_k
    delta.to_delta = lambda x, c: (x - c) / delta.delta_k
    delta.from_delta = lambda z, c: c + delta.delta_k * z
    frame_loss(delta, x, cond, torch.Generator().manual_seed(0), "amdm", sched, "x0", cond_noise=2)
    spread = (seen[-1] - cond).std(0) / delta.delta_k
    assert (spread - 2).abs().max() < 0.1
    geo_seen = []

    def geometry(x0_hat, prev, target, weight):  # a FrameGeometry's signature
        geo_seen.append((x0_hat.clone(), prev.clone()))
        return torch.zeros_like(weight)

    g = torch.Generator().manual_seed(0)
    frame_loss(delta, x, cond, g, "amdm", sched, "x0", cond_noise=2, geometry=geometry)
    x0_hat, prev = geo_seen[-1]
    assert torch.equal(prev, cond)  # the body's motion is measured from the recorded frame,
    torch.testing.assert_close(x0_hat, seen[-1])  # the frame from the noised one (z0_hat = 0)
    with pytest.raises(ValueError, match="cond_noise needs model_kind: amdm"):
        tiny(model_kind="mvae", cond_noise=0.1)
    with pytest.raises(ValueError, match="cond_noise must be a finite float"):
        tiny(cond_noise=-1.0)


def test_delta_from_recorded_measures_the_change_from_the_frame_before_the_noise():
    """delta_from='seen' measures a delta model's change from the noised condition, so that
    undoing the noise is part of the target; 'recorded' from the frame before the noise."""
    from minimdm.amdm.losses import frame_loss

    seen = []

    class Zero(nn.Module):  # predicts a change of zero, and keeps the condition it saw
        is_delta = True

        def forward(self, x_t, t, cond):
            seen.append(cond.clone())
            return torch.zeros_like(x_t)

    net = Zero()
    net.delta_k = net.delta_spread = torch.linspace(0.05, 0.5, D)
    net.to_delta = lambda x, c: (x - c) / net.delta_k
    net.from_delta = lambda z, c: c + net.delta_k * z
    x, cond = torch.randn(512, D), torch.randn(512, D)
    sched = NoiseSchedule("cosine", 8)
    for origin in ("seen", "recorded"):
        g = torch.Generator().manual_seed(0)
        kw = dict(cond_noise=2.0, delta_from=origin)
        loss, pred = frame_loss(net, x, cond, g, "amdm", sched, "x0", **kw)
        noised = seen[-1]
        assert not torch.allclose(noised, cond)  # the network saw the noise either way
        start = noised if origin == "seen" else cond
        torch.testing.assert_close(pred, start)  # z0_hat = 0: the frame is the change's origin
        torch.testing.assert_close(loss, ((x - start) / net.delta_k).pow(2).mean(1))
    with pytest.raises(ValueError, match="delta_from must be 'seen' or 'recorded'"):
        frame_loss(net, x, cond, None, "amdm", sched, "x0", delta_from="noised")
    with pytest.raises(ValueError, match="delta_from must be 'seen' or 'recorded'"):
        tiny(delta_from="clean")


def test_cond_noise_root_scales_the_noise_on_the_pace_only():
    """cond_noise_root multiplies the condition noise of d_x, d_y, d_r; 0 shows the network the
    recorded pace while the rest of the frame stays noised."""
    from minimdm.amdm.train import _cond_spread

    layout = FeatureLayout(("hips", "knee", "foot"))
    k = torch.linspace(0.05, 0.5, layout.dim)
    root = torch.zeros(layout.dim, dtype=torch.bool)
    root[:3] = True
    for delta, unit in ((True, k), (False, torch.ones(layout.dim))):
        kw = dict(delta=delta, delta_features="joint_motion", T=6, width=8, depth=2)
        for factor in (0.0, 0.5):
            cfg = TrainConfig(cond_noise=0.75, cond_noise_root=factor, **kw)
            spread = _cond_spread(cfg, build_network(cfg, layout.dim, k.tolist()))
            torch.testing.assert_close(spread[~root], 0.75 * unit[~root])
            torch.testing.assert_close(spread[root], factor * 0.75 * unit[root])
    with pytest.raises(ValueError, match=r"cond_noise_root must be in \[0, 1\]"):
        tiny(cond_noise_root=1.5)


def test_motion_condition_noise_reaches_the_root_and_joint_displacements_in_frame_units():
    """cond_noise_motion adds noise of its spread, in frame units, to d_x, d_y, d_r and j_v only,
    independent of a delta model's cond_noise (in units of each feature's change)."""
    from minimdm.amdm.losses import frame_loss
    from minimdm.amdm.train import _cond_spread

    layout = FeatureLayout(("hips", "knee", "foot"))
    m = torch.tensor(motion_mask(layout.dim))
    assert m[layout.root_vel].eq(1).all() and m[2] == 1 and m[layout.joint_vel].eq(1).all()
    assert m[layout.joint_pos].eq(0).all() and m[layout.joint_rot].eq(0).all()
    k = torch.linspace(0.05, 0.5, layout.dim)
    kw = dict(delta=True, delta_features="not_positions", T=6, width=8, depth=2)
    cfg = TrainConfig(cond_noise=0.5, cond_noise_motion=0.4, **kw)
    net = build_network(cfg, layout.dim, k.tolist())
    spread = _cond_spread(cfg, net)
    torch.testing.assert_close(spread, ((0.5 * k) ** 2 + (0.4 * m) ** 2).sqrt())
    assert _cond_spread(TrainConfig(cond_noise=0.5, **kw), net) == 0.5  # the loss scales by k

    seen = []

    class Recorder(nn.Module):
        def forward(self, x_t, t, cond):
            seen.append(cond.clone())
            return torch.zeros_like(x_t)

    x, cond = torch.randn(8192, layout.dim), torch.randn(8192, layout.dim)
    g = torch.Generator().manual_seed(0)
    sched = NoiseSchedule("cosine", 8)
    frame_loss(Recorder(), x, cond, g, "amdm", sched, "x0", cond_noise=0.3 * m)
    torch.testing.assert_close((seen[-1] - cond).std(0), 0.3 * m, atol=0.01, rtol=0)
    uniform = dict(cond_noise_draw="uniform")
    frame_loss(Recorder(), x, cond, g, "amdm", sched, "x0", cond_noise=0.3 * m, **uniform)
    power = (seen[-1] - cond)[:, m > 0].pow(2).mean(1)  # each condition's own size, up to 0.3
    assert power.min() < 0.03**2  # some conditions nearly clean; on average E[u^2] = 1/3 of it
    torch.testing.assert_close(power.mean(), torch.tensor(0.3**2 / 3), atol=0.002, rtol=0)
    assert torch.equal(seen[-1][:, m == 0], cond[:, m == 0])
    with pytest.raises(ValueError, match="cond_noise_draw must be 'fixed' or 'uniform'"):
        tiny(cond_noise_draw="normal")
    with pytest.raises(ValueError, match="cond_noise_motion needs model_kind: amdm"):
        tiny(model_kind="mse", cond_noise_motion=0.1)
    with pytest.raises(ValueError, match="cond_noise_motion must be a finite float"):
        tiny(cond_noise_motion=float("nan"))


def test_a_model_told_its_condition_noise_reads_each_drawn_size():
    """With cond_level the denoiser is told each training condition's drawn noise size (the
    uniform factor), and at run time the configured level; without it, no level is accepted."""
    from minimdm.amdm.losses import frame_loss

    class Told(MLPDenoiser):
        def forward(self, x_t, t, cond, level=None):
            self.seen = (cond.clone(), None if level is None else level.clone())
            return super().forward(x_t, t, cond, level)

    net = Told(DenoiserConfig(D, D, 32, 3, predicts="x0", cond_level=0.25))
    x, cond = torch.randn(512, D), torch.randn(512, D)
    sched = NoiseSchedule("cosine", 8)
    g = torch.Generator().manual_seed(0)
    frame_loss(net, x, cond, g, "amdm", sched, "x0", cond_noise=0.5, cond_noise_draw="uniform")
    seen, level = net.seen
    assert level.shape == (512,) and ((level >= 0) & (level <= 1)).all()
    # each condition's noise has the spread 0.5 times the level it was told
    sq = (seen - cond).pow(2)
    assert abs(float((sq.sum() / (D * level.pow(2).sum())).sqrt()) - 0.5) < 0.03
    per_row = sq.mean(1).sqrt()
    assert torch.corrcoef(torch.stack([per_row, level]))[0, 1] > 0.8
    # at run time the configured level; another level gives another output
    x_t, t = torch.randn(3, D), torch.zeros(3, dtype=torch.long)
    out = net(x_t, t, cond[:3])
    torch.testing.assert_close(out, net(x_t, t, cond[:3], torch.full((3,), 0.25)))
    assert not torch.allclose(out, net(x_t, t, cond[:3], torch.ones(3)))
    plain = MLPDenoiser(DenoiserConfig(D, D, 32, 3))
    with pytest.raises(ValueError, match="level needs a model told"):
        plain(x_t, t, cond[:3], torch.ones(3))
    with pytest.raises(ValueError, match=r"cond_level must be in \[0, 1\]"):
        MLPDenoiser(DenoiserConfig(D, D, 32, 3, cond_level=1.5))
    with pytest.raises(ValueError, match="cond_level needs model_kind 'amdm' and cond_noise_draw"):
        tiny(cond_noise=0.5, cond_level=0.2)  # a fixed draw tells the model nothing
    with pytest.raises(ValueError, match=r"cond_level must be in \[0, 1\] or null"):
        tiny(cond_noise=0.5, cond_noise_draw="uniform", cond_level=-0.1)


def test_an_extra_corpus_adds_its_takes_to_the_training_takes(tmp_path):
    """extra_corpus: a second source's takes join the training takes, and the normalizer is fitted
    on both; extra_contents keeps only its takes of those contents. A source of another skeleton
    is refused naming both skeletons' joints, and so are contents the source does not have."""
    from minimdm.amdm.train import _load_data
    from minimdm.motion.bvh import save_bvh
    from minimdm.motion.corpora import load_corpus
    from minimdm.motion.data import load_clips
    from minimdm.validate import InputError, MismatchError

    added = ["dataset-1_run_happy_001", "dataset-1_walk_normal_001"]  # held-out takes
    for clip in load_corpus("bandai-namco-1", split="test", takes=added):
        save_bvh(tmp_path / "same" / f"{clip.name}.bvh", clip)
    base = dict(corpus="bandai-namco-1", split="train", loop_frames=None,
                clips=["dataset-1_walk_normal_002"])  # fmt: skip
    one = _load_data(TrainConfig(**base))
    both = _load_data(TrainConfig(**base, extra_corpus=str(tmp_path / "same")))
    assert both["clip_names"] == one["clip_names"] + added
    assert len(both["features"]) == 3 and len(both["heldout"]) == len(one["heldout"])
    assert not torch.allclose(both["normalizer"].mean, one["normalizer"].mean)
    # the first take's frames are the same recorded frames under either normalizer
    torch.testing.assert_close(
        both["normalizer"].denormalize(both["features"][0]),
        one["normalizer"].denormalize(one["features"][0]),
        rtol=1e-4,
        atol=1e-4,
    )
    # a trained checkpoint finds its clips again in both sources (Table 1's foot offsets need them)
    from minimdm.amdm.evaluation import checkpoint_clips

    cfg = tiny(**base, extra_corpus=str(tmp_path / "same"))
    train_amdm(cfg, tmp_path / "run", progress=False)
    ckpt = load_checkpoint(tmp_path / "run")
    assert checkpoint_clips(ckpt).names == both["clip_names"]
    held_out = load_corpus("bandai-namco-1", split="test").names
    assert checkpoint_clips(ckpt, split="test").names == held_out
    # a labelled corpus as the extra source: only its runs (every take of them, train and test)
    folder = dict(corpus=str(tmp_path / "same"), split=None, loop_frames=None)
    with pytest.raises(InputError, match=r"takes \['dataset-1_run_happy_001'\] are in both"):
        _load_data(TrainConfig(**folder, extra_corpus="bandai-namco-1", extra_contents=["run"]))
    (tmp_path / "same" / "dataset-1_run_happy_001.bvh").unlink()
    runs = _load_data(TrainConfig(**folder, extra_corpus="bandai-namco-1", extra_contents=["run"]))
    extra_names = runs["clip_names"][1:]
    assert extra_names and all("_run_" in n for n in extra_names)
    assert "dataset-1_run_happy_001" in extra_names  # a test take of bandai-namco-1 is included
    with pytest.raises(InputError, match=r"extra_contents \['swim'\] are not contents"):
        _load_data(TrainConfig(**folder, extra_corpus="bandai-namco-1", extra_contents=["swim"]))
    humanoid = load_clips(names=["walk"])[0]  # DeepMimic's humanoid: other joints
    save_bvh(tmp_path / "other" / "walk.bvh", humanoid)
    with pytest.raises(MismatchError, match="has joints .* bandai-namco-1 has"):
        _load_data(TrainConfig(**base, extra_corpus=str(tmp_path / "other")))
    with pytest.raises(ValueError, match="extra_contents names contents of extra_corpus"):
        TrainConfig(extra_contents=["walk"])
    with pytest.raises(ValueError, match="extra_corpus is the corpus itself"):
        TrainConfig(corpus="bandai-namco-1", extra_corpus="bandai-namco-1")
