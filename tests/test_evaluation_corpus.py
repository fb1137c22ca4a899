"""The evaluation protocol on a corpus checkpoint: held-out starts, actors' own bone lengths,
and the memorisation probe."""

import numpy as np
import pytest
import torch

from minimdm.amdm import evaluation
from minimdm.amdm.train import TrainConfig, train_amdm
from minimdm.motion import corpora
from minimdm.motion.features import encode

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

TAKES = ["dataset-1_walk_normal_002", "dataset-1_run_sad_001"]


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("MINIMDM_DATA", str(tmp_path_factory.mktemp("data")))
    config = TrainConfig(
        width=32, depth=3, time_dim=8, T=4, batch_size=8, total_steps=4, rollout=2,
        teacher_steps=1, ramp_steps=1, eval_interval=0, ckpt_interval=0, loop_frames=None,
        corpus="bandai-namco-1", split="train", clips=TAKES,
    )  # fmt: skip
    yield train_amdm(config, tmp_path_factory.mktemp("ckpt"), progress=False).checkpoint
    mp.undo()


SMALL = evaluation.Protocol(n_states=2, n_samples=2, apd_frames=12, ade_frames=6, seeds=(0, 1))


def test_tables_start_from_held_out_takes(ckpt):
    test = set(corpora.corpus_split("bandai-namco-1")["test"])
    assert set(evaluation.checkpoint_clips(ckpt).names) == set(TAKES)
    assert set(evaluation.checkpoint_clips(ckpt, split="test").names) == test
    held = evaluation._start_clips(ckpt, SMALL)
    states = evaluation.random_states(held, SMALL.n_states, SMALL.ade_frames, SMALL.state_seed)
    assert {s.clip for s in states} <= test
    # the training clips when asked for (split=None), as for a checkpoint without a split
    own = evaluation._start_clips(ckpt, evaluation.Protocol(split=None))
    assert set(own.names) == set(TAKES)
    # a held-out take can be named as a start, and carries its actor's own bone lengths
    take = sorted(test)[0]
    s = evaluation.initial_state(ckpt, take, 5, ref_frames=6)
    sk = held[take].skeleton
    assert s.clip == take and s.reference.shape == (6, len(sk.names), 3)
    assert s.bone_lengths.shape == (len(sk.names) - 1,)  # one per bone
    table = evaluation.table1({"m": ckpt}, SMALL, with_dataset=True)
    assert table["dataset"]["Bone.Err"][0] < 1e-3  # each take against its own bones
    assert set(table["m"]) >= {"APD", "ADE", "FDE"}


def test_distance_to_training_is_zero_on_training_frames_and_grows_with_an_offset(ckpt):
    training = torch.cat([encode(c) for c in evaluation.checkpoint_clips(ckpt, unrolled=False)])
    d0 = evaluation.pose_distance_to_training(ckpt, training[::7], training)
    assert np.allclose(d0, 0.0, atol=1e-4)
    layout = ckpt.metadata["feature_layout"]
    J = len(layout["joint_names"])
    moved = training[::7].clone()
    moved[:, 3 : 3 + 3 * J] += 0.02  # every joint 2 cm along x, y and z: 2*sqrt(3) cm away
    d = evaluation.pose_distance_to_training(ckpt, moved, training)
    assert (d <= 2 * 3**0.5 + 1e-4).all() and d.mean() > 0.5


def test_memorisation_probe_reports_generated_next_to_held_out(ckpt):
    probe = evaluation.memorisation_probe(ckpt, SMALL, near=1.0)
    assert set(probe) == {"generated", "held-out"}
    for row in probe.values():
        assert set(row) == {"median", "p90", "share<1cm"}
        assert 0 <= row["median"][0] <= row["p90"][0]
    # the test takes are other takes than the two training takes: none of it is a copy
    assert probe["held-out"]["median"][0] > 1.0
