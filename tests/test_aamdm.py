"""Tests for minimdm.aamdm and minimdm.aamdm.eval: the engineered features x, forward kinematics,
the autoencoder and its round trip, latent sizes, rollouts, guidance and the pose metrics."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from minimdm.aamdm.eval import (
    direction_guide,
    pose_diversity,
    pose_frechet_distance,
    rollout_aamdm,
)
from minimdm.aamdm.model import AAMDMConfig
from minimdm.aamdm.motion import AAMDMMotion, MotionModelConfig, fk_positions, trajectory_features
from minimdm.aamdm.motion_train import AAMDMTrainConfig, load_train_config
from minimdm.amdm.sampling import NonFiniteFrameError
from minimdm.motion import metrics
from minimdm.validate import InputError

ROOT = Path(__file__).resolve().parents[1]
BOOK = ROOT / "checkpoints" / "aamdm"


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


# ----------------------------------------------------------------------------------------------
# x: the future-trajectory features


def test_trajectory_features_of_a_straight_walk_and_a_turn():
    F = 40
    t = torch.arange(F, dtype=torch.float64)
    # straight along +x at 2 cm per frame, facing +x
    x = trajectory_features(torch.stack([0.02 * t, 0 * t], -1), 0 * t, (10, 20, 30))
    assert torch.allclose(x[0, :6], torch.tensor([0.2, 0, 0.4, 0, 0.6, 0], dtype=x.dtype))
    assert torch.allclose(x[0, 6:], torch.tensor([1.0, 0] * 3, dtype=x.dtype))
    # a constant yaw rate w on the spot: the direction h frames ahead is (cos wh, sin wh)
    w = 0.05
    x = trajectory_features(torch.zeros(F, 2, dtype=torch.float64), w * t, (10, 20, 30))
    for i, h in enumerate((10, 20, 30)):
        assert x[0, 6 + 2 * i] == pytest.approx(math.cos(w * h))
        assert x[0, 7 + 2 * i] == pytest.approx(math.sin(w * h))
    # past the end of the clip the last frame stands in: no motion, same facing
    assert torch.allclose(x[-1], torch.tensor([0.0] * 6 + [1.0, 0] * 3, dtype=x.dtype))


@settings(max_examples=25, deadline=None)
@given(
    yaw=st.floats(-math.pi, math.pi),
    tx=st.floats(-5, 5),
    ty=st.floats(-5, 5),
    seed=st.integers(0, 1000),
)
def test_trajectory_features_do_not_depend_on_where_the_character_stands(yaw, tx, ty, seed):
    """x is expressed in each frame's heading frame: a rigid motion of the world leaves it."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.cumsum(torch.randn(50, 2, generator=g, dtype=torch.float64) * 0.05, 0)
    heading = torch.cumsum(torch.randn(50, generator=g, dtype=torch.float64) * 0.1, 0)
    c, s = math.cos(yaw), math.sin(yaw)
    R = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    moved = xy @ R.T + torch.tensor([tx, ty], dtype=torch.float64)
    a = trajectory_features(xy, heading)
    b = trajectory_features(moved, heading + yaw)
    assert torch.allclose(a, b, atol=1e-9)


# ----------------------------------------------------------------------------------------------
# F: forward kinematics on the A-MDM frame


def test_fk_positions_reproduce_the_joint_positions_of_real_frames():
    pytest.importorskip("pybullet_data")
    from minimdm.motion import data, features

    clip = data.load_clips(fps=30, names=["walk", "cartwheel"])
    for c in clip:
        y = features.encode(c).double()
        J = len(c.skeleton)
        f = fk_positions(y, c.skeleton)
        assert (f - y[:, 3 : 3 + 3 * J].reshape(-1, J, 3)).abs().max() < 1e-5


# ----------------------------------------------------------------------------------------------
# The model: sizes, rollouts, guidance


def tiny_motion(seed=0, z_dim=4) -> AAMDMMotion:
    torch.manual_seed(seed)
    xz = 12 + z_dim
    tcfg = AAMDMConfig(xz, xz, 3, 2, latent_dim=2, width=16, depth=2, time_dim=8, clip_x0=6.0)
    return AAMDMMotion(MotionModelConfig(183, 12, z_dim, 16, 2, [10, 20, 30], asdict(tcfg))).eval()


def test_mismatched_latent_sizes_between_autoencoder_and_sampler_raise():
    tcfg = AAMDMConfig(30, 30, 3, 2)
    with pytest.raises(ValueError, match=r"x_dim \+ z_dim = 12 \+ 24 = 36, got x_dim 30"):
        AAMDMMotion(MotionModelConfig(183, 12, 24, transition=asdict(tcfg)))
    m = tiny_motion()
    with pytest.raises(ValueError, match=r"xz must have last dim x_dim \+ z_dim = 12 \+ 4"):
        m.autoencoder.decode(torch.zeros(2, 20))
    with pytest.raises(ValueError, match="y must have last dim 183"):
        m.autoencoder.encode(torch.zeros(2, 180))


def test_rollout_shapes_seed_and_bad_input():
    m = tiny_motion()
    y, x = torch.randn(2, 183) * 0.1, torch.randn(2, 12) * 0.1
    r = rollout_aamdm(m, y, x, 6, 3, torch.Generator().manual_seed(0))
    assert r.features.shape == (2, 3, 6, 183) and r.normalized.shape == (2, 3, 6, 16)
    assert r.positions.shape == (2, 3, 6, 15, 3) and torch.isfinite(r.positions).all()
    again = rollout_aamdm(m, y, x, 6, 3, torch.Generator().manual_seed(0))
    assert torch.equal(r.features, again.features)
    draft = rollout_aamdm(m, y, x, 2, 1, torch.Generator().manual_seed(0), T_adm=0)
    assert draft.features.shape == (2, 1, 2, 183)
    with pytest.raises(ValueError, match=r"init_y and init_x must have 183 and 12 columns"):
        rollout_aamdm(m, y, torch.zeros(2, 11), 3)
    with pytest.raises(ValueError, match="init_x must be finite"):
        rollout_aamdm(m, y, x * math.nan, 3)
    with pytest.raises(ValueError, match="n_frames must be an integer >= 1"):
        rollout_aamdm(m, y, x, 0)


def test_rollout_raises_naming_the_frame_instead_of_returning_nan():
    m = tiny_motion()
    with torch.no_grad():
        m.autoencoder.decoder[-1].bias.fill_(math.inf)
    with pytest.raises(NonFiniteFrameError, match="non-finite frame 1"):
        rollout_aamdm(m, torch.zeros(1, 183), torch.zeros(1, 12), 3)


def test_direction_guide_cost_is_zero_on_the_command_and_grows_away_from_it():
    m = tiny_motion()
    xz = torch.zeros(2, 16)
    # build x-hat whose facing directions are exactly (cos d, sin d) for d = 0.3
    d = 0.3
    x = torch.zeros(2, 12)
    x[:, 6:] = torch.tensor([math.cos(d), math.sin(d)] * 3)
    x_n = (x - m.x_mean) / m.x_std
    xz[:, :12] = (x_n - m.xz_mean[:12]) / m.xz_std[:12]
    J = direction_guide(m, torch.tensor([d, d + 1.0]), 1.0).cost(xz)
    assert J[0] == pytest.approx(0.0, abs=1e-10)
    assert J[1] == pytest.approx(3 * 2 * (1 - math.cos(1.0)), rel=1e-5)


# ----------------------------------------------------------------------------------------------
# Metrics


def test_pose_frechet_distance_closed_forms():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(20000, 3, generator=g, dtype=torch.float64)
    assert pose_frechet_distance(a, a) == pytest.approx(0.0, abs=1e-6)
    m = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    assert pose_frechet_distance(a, a + m) == pytest.approx(m.pow(2).sum().item(), rel=1e-6)
    # N(0, I) vs N(0, 4 I): 1 + 4 - 2 sqrt(1 * 4) = 1 per dimension, 3 in all
    b = torch.randn(20000, 3, generator=g, dtype=torch.float64) * 2
    assert pose_frechet_distance(a, b) == pytest.approx(3.0, abs=0.1)


def test_pose_diversity_of_two_poses():
    poses = torch.zeros(1000, 4)
    poses[500:, 0] = 3.0  # two poses 3 apart, half each: a random pair differs half the time
    assert pose_diversity(poses, n_pairs=20000) == pytest.approx(1.5, abs=0.05)


# ----------------------------------------------------------------------------------------------
# Config and the shipped checkpoint


def test_config_loads_and_rejects_unknown_keys(tmp_path):
    cfg = load_train_config(ROOT / "configs" / "aamdm.yaml")
    assert isinstance(cfg, AAMDMTrainConfig) and (cfg.T_gan, cfg.T_adm) == (3, 2)
    assert isinstance(cfg.ae_lr, float)
    bad = tmp_path / "bad.yaml"
    bad.write_text("z_dim: 8\nzdim: 4\n")
    with pytest.raises(ValueError, match=r"unknown config keys \['zdim'\]"):
        load_train_config(bad)


def test_corpus_data_starts_from_held_out_takes_with_each_actors_bones():
    from minimdm.aamdm.eval import initial_states
    from minimdm.aamdm.motion_train import load_motion_data
    from minimdm.studies.aamdm_motion import locomotion_clips

    cfg = load_train_config(ROOT / "configs" / "aamdm.yaml")
    assert (cfg.corpus, cfg.split) == ("bandai-namco-1", "train")
    test = AAMDMTrainConfig(corpus=cfg.corpus, split="test", loop_frames=None)
    d = load_motion_data(test)
    assert len(d["clips"]) == 19 and len(d["y"]) == len(d["x"]) == 19
    assert all(y.shape[1] == d["layout"].dim == 255 for y in d["y"])
    walk, run = locomotion_clips(d)
    assert d["clips"][walk].labels["content"] == "walk"
    assert d["clips"][run].labels["content"] == "run"
    init = initial_states(d)  # every held-out take by default
    assert init["names"] == d["clips"].names and init["y"].shape == (19, 255)
    bones = init["bone_lengths"]  # (19, J - 1): each take's own actor
    assert bones.shape == (19, 20)
    for i in (0, 18):
        sk = d["clips"][i].skeleton
        own = torch.as_tensor(metrics.skeleton_bone_lengths(sk.offsets, sk.parents))
        assert torch.allclose(bones[i], own)
    with pytest.raises(ValueError, match="no clip with content 'swim'"):
        locomotion_clips(d, ("swim",))
    with pytest.raises(ValueError, match="no split"):
        load_motion_data(AAMDMTrainConfig(split="test"))  # the DeepMimic clips have none


def test_a_tiny_corpus_training_records_and_reloads_its_takes(tmp_path):
    """Train end to end on two training takes with tiny step counts: the checkpoint records the
    corpus, split and takes, and :func:`checkpoint_training_xz` rebuilds exactly the frames the
    model was trained on, all inside the clamp that training stored."""
    from minimdm.aamdm.motion_train import (
        checkpoint_training_xz,
        load_motion_data,
        train_aamdm_motion,
    )
    from minimdm.checkpoint import load_checkpoint
    from minimdm.diffusion.clamp import clamp_share

    takes = ["dataset-1_bow_angry_001", "dataset-1_bow_childish_001"]
    cfg = AAMDMTrainConfig(
        corpus="bandai-namco-1", split="train", clips=takes, loop_frames=None,
        z_dim=4, ae_width=16, ae_depth=2, ae_steps=3, ae_batch=8, latent_dim=2, width=16,
        depth=2, disc_width=16, window=2, polish_steps=2, polish_batch=4, gan_steps=2,
        gan_batch=4,
    )  # fmt: skip
    _, report = train_aamdm_motion(cfg, tmp_path, progress=False)
    ck = load_checkpoint(tmp_path)
    data = ck.metadata["data"]
    assert (data["corpus"], data["split"], data["clips"]) == ("bandai-namco-1", "train", takes)
    assert (ck.config["corpus"], ck.config["split"]) == ("bandai-namco-1", "train")
    d = load_motion_data(cfg)
    assert report["frames"] == sum(len(y) for y in d["y"]) == 90 - 1 + 98 - 1  # pairs of frames
    xz = checkpoint_training_xz(ck)
    assert xz.shape == (report["frames"], ck.model.config.x_dim + cfg.z_dim)
    # xz was standardised over exactly these frames: mean 0, std 1 per feature
    assert torch.allclose(xz.mean(0), torch.zeros(xz.shape[1]), atol=1e-4)
    assert clamp_share(ck.model.transition.config.clip_x0, xz) == 0.0


def test_a_config_without_corpus_keys_is_deepmimic_and_a_bad_corpus_lists_the_known_ones():
    pytest.importorskip("pybullet_data")
    from minimdm.aamdm.motion_train import load_motion_data
    from minimdm.motion.corpora import CORPORA

    old = {k: v for k, v in asdict(AAMDMTrainConfig()).items() if k not in ("corpus", "split")}
    cfg = AAMDMTrainConfig(**{**old, "clips": ["walk"]})  # an older checkpoint's config
    assert (cfg.corpus, cfg.split) == ("deepmimic", None)
    d = load_motion_data(cfg)
    assert d["clips"].names == ["walk"] and len(d["clips"][0]) == 150  # loop_frames
    with pytest.raises(ValueError, match="known corpus") as err:
        load_motion_data(AAMDMTrainConfig(corpus="bandai-namco-9"))
    assert all(name in str(err.value) for name in CORPORA)


@pytest.mark.skipif(not (BOOK / "model.safetensors").exists(), reason="no shipped checkpoint")
def test_shipped_autoencoder_round_trip_is_within_the_measured_bound():
    """decode(encode(y, x)) on every training frame: the joint positions of the pose come back
    within 2 cm on average (measured 0.99 cm for the shipped model, on its 155 training takes) and
    the forward kinematics of the decoded rotations within 1 cm (measured 0.62 cm)."""
    pytest.importorskip("pybullet_data")
    from minimdm.aamdm.motion_train import load_motion_data
    from minimdm.checkpoint import load_checkpoint

    ck = load_checkpoint(BOOK)
    m = ck.model
    d = load_motion_data(AAMDMTrainConfig(**ck.config))  # its training takes
    y, x = torch.cat(d["y"]), torch.cat(d["x"])
    with torch.no_grad():
        y_hat = m.decode(m.encode(y, x))
    J = len(d["skeleton"])
    pos = y[:, 3 : 3 + 3 * J].reshape(-1, J, 3)
    pos_hat = y_hat[:, 3 : 3 + 3 * J].reshape(-1, J, 3)
    err_cm = (pos_hat - pos).norm(dim=-1).mean().item() * 100
    fk_cm = (fk_positions(y_hat, d["skeleton"]) - pos).norm(dim=-1).mean().item() * 100
    assert err_cm < 2.0, err_cm
    assert fk_cm < 1.0, fk_cm


# ----------------------------------------------------------------------------------------------
# The one rollout loop


def _old_rollout_aamdm(model, init_y, init_x, n_frames, K, generator, direction, guide_scale):
    """rollout_aamdm's loop as it was before the one loop (a reference copy for the test)."""
    from minimdm.motion.skeleton import wrap_angle

    C = init_y.shape[0]
    heading = torch.zeros(C).repeat_interleave(K)
    direction = torch.as_tensor(direction, dtype=torch.float32).expand(C).repeat_interleave(K)
    xz = model.encode(init_y, init_x).repeat_interleave(K, dim=0)
    feats, lat = [], []
    for _ in range(n_frames):
        guide = None
        if guide_scale > 0:
            guide = direction_guide(model, wrap_angle(direction - heading), guide_scale)
        xz = model.transition.sample(xz, generator, guide=guide)
        y = model.decode(xz)
        heading = heading + y[:, 2]
        feats.append(y.float())
        lat.append(xz.float())
    return torch.stack(feats, 1), torch.stack(lat, 1)


@pytest.mark.parametrize("scale", [0.0, 1.0])
def test_rollout_is_bit_identical_to_the_old_loop(scale):
    m = tiny_motion()
    y, x = torch.randn(2, 183) * 0.1, torch.randn(2, 12) * 0.1
    r = rollout_aamdm(m, y, x, 5, 2, torch.Generator().manual_seed(0), direction=0.7,
                      guide_scale=scale, decode_positions=False)  # fmt: skip
    with torch.no_grad():
        feats, lat = _old_rollout_aamdm(m, y, x, 5, 2, torch.Generator().manual_seed(0), 0.7,
                                        scale)  # fmt: skip
    assert torch.equal(r.features.flatten(0, 1), feats)
    assert torch.equal(r.normalized.flatten(0, 1), lat)


@pytest.mark.parametrize("k", [1, 3])
def test_rollout_names_the_frame_where_the_sampler_returns_nan(k):
    m = tiny_motion()
    sample, calls = m.transition.sample, []

    def poisoned(*args, **kwargs):  # NaN in batch row 2 from the k-th frame on
        xz = sample(*args, **kwargs)
        calls.append(1)
        if len(calls) >= k:
            xz = xz.clone()
            xz[2, 0] = float("nan")
        return xz

    m.transition.sample = poisoned
    y, x = torch.zeros(2, 183), torch.zeros(2, 12)
    with pytest.raises(NonFiniteFrameError, match=rf"frame {k} .*character 1, sample 0") as e:
        rollout_aamdm(m, y, x, 5, 2)
    assert e.value.frame == k


def test_motion_quality_pools_motions_and_averages_apd_over_initial_states():
    from minimdm.aamdm.eval import local_poses, motion_quality
    from minimdm.amdm.sampling import Rollout
    from minimdm.motion import metrics
    from minimdm.motion.skeleton import Skeleton

    sk = Skeleton(["root", "foot"], [-1, 0], np.array([[0.0, 0, 0], [0.0, 0, -0.5]]), ["foot"])
    pos = torch.randn(2, 3, 6, 2, 3, generator=torch.Generator().manual_seed(0)) * 0.1
    feats = torch.randn(2, 3, 6, 3 + 12 * 2, generator=torch.Generator().manual_seed(1))
    q = motion_quality(Rollout(feats, pos, feats), sk, local_poses(feats, 2), 0.0)
    ref = metrics.skeleton_bone_lengths(sk.offsets, sk.parents)
    flat = pos.flatten(0, 1)
    assert q["APD"] == pytest.approx((metrics.apd(pos[0]) + metrics.apd(pos[1])) / 2)
    assert q["FS"] == metrics.foot_sliding(flat, sk.foot_indices)
    assert q["Bone.Err"] == metrics.bone_length_error(flat, sk.parents, ref)
    assert q["Jnt.Accel"] == metrics.joint_acceleration(flat)


def test_study_fps_times_the_one_loop_and_motion_metrics_of_one_clip():
    from minimdm.motion import metrics
    from minimdm.studies.aamdm_motion import frames_per_second

    calls = []

    def step(f, x):
        calls.append(f)
        return x + 1

    assert frames_per_second(step, torch.zeros(1, 2), n_frames=7, warmup=3) > 0
    assert calls == [1, 2, 3] + list(range(1, 8)) * 2  # warm-up, then two timed passes
    clip = torch.randn(8, 2, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    m = metrics.motion_metrics(clip, [-1, 0], [1], [0.5])
    assert "APD" not in m and m["FS"] == metrics.foot_sliding(clip, [1])
    with pytest.raises(ValueError, match="reference needs"):
        metrics.motion_metrics(clip[None, None], [-1, 0], [1], [0.5], reference=clip)


def test_mirror_doubles_the_motion_data_with_the_reflected_takes():
    """mirror: True appends each take's mirror image to y and x: the forward speed is the same,
    the sideways speed and the turning flip, and the future trajectory's lateral offsets flip."""
    from minimdm.aamdm.motion_train import load_motion_data

    base = dict(corpus="bandai-namco-1", split="train", loop_frames=None,
                clips=["dataset-1_walk-left_active_001"])  # fmt: skip
    one = load_motion_data(AAMDMTrainConfig(**base))
    two = load_motion_data(AAMDMTrainConfig(**base, mirror=True))
    assert len(two["y"]) == 2 * len(one["y"]) and list(two["clips"].names) == base["clips"]
    y, m = one["y"][0], two["y"][1]
    torch.testing.assert_close(m[:, 0], y[:, 0], atol=1e-5, rtol=0)  # forward speed
    torch.testing.assert_close(m[:, 1:3], -y[:, 1:3], atol=1e-5, rtol=0)  # sideways, turning
    assert float(y[:, 1].mean()) > 0.003 > -0.003 > float(m[:, 1].mean())  # left becomes right
    torch.testing.assert_close(two["y"][0], y)
    assert not torch.allclose(two["x"][1], one["x"][0], atol=1e-3)  # the futures are reflected


def test_locomotion_share_weights_the_pairs_and_windows_by_content():
    """locomotion_share: 0.8 gives the locomotion takes (and their mirror images) 80% of the
    draws, whatever their length; the draws follow the weights, and bad weights are refused."""
    from minimdm.aamdm.motion_train import _weights, load_motion_data
    from minimdm.aamdm.train import _check_weights, _draw

    clips = ["dataset-1_walk-left_active_001", "dataset-1_bow_active_001"]
    cfg = AAMDMTrainConfig(corpus="bandai-namco-1", split="train", loop_frames=None, clips=clips,
                           mirror=True, locomotion_share=0.8)  # fmt: skip
    d = load_motion_data(cfg)
    assert sorted(d["contents"]) == ["bow", "bow", "walk-left", "walk-left"]
    for n in (1, 4):
        w = _weights(cfg, d, d["y"], n)
        counts = [len(y) - n for y in d["y"]]
        assert w.shape == (sum(counts),)
        per_clip = [float(part.sum()) for part in w.split(counts)]
        loco = sum(p for p, c in zip(per_clip, d["contents"], strict=True) if c == "walk-left")
        assert sum(per_clip) == pytest.approx(1.0) and loco == pytest.approx(0.8)
    assert _weights(dataclasses.replace(cfg, locomotion_share=None), d, d["y"], 1) is None
    windows = torch.arange(10.0)[:, None, None].expand(10, 2, 3)
    one_hot = torch.zeros(10).index_fill(0, torch.tensor([3]), 1.0)
    drawn = _draw(50, windows, _check_weights(one_hot, windows), torch.Generator().manual_seed(0))
    assert (drawn == 3).all()
    uniform = _draw(50, windows, None, torch.Generator().manual_seed(0))
    assert len(set(uniform[:, 0, 0].tolist())) > 5
    with pytest.raises(ValueError, match=r"shape \(10,\)"):
        _check_weights(torch.ones(9), windows)
    with pytest.raises(ValueError, match="not all zero"):
        _check_weights(torch.zeros(10), windows)
    with pytest.raises(InputError, match="locomotion_share"):
        AAMDMTrainConfig(locomotion_share=1.5)
