"""Multi-process training with DDP: two CPU processes (gloo) end with the same weights."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import torch
import torch.multiprocessing as mp

from minimdm.amdm.train import TrainConfig, train_amdm
from minimdm.checkpoint import load_checkpoint


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, port: int, folder: str) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        LOCAL_RANK=str(rank),
        WORLD_SIZE=str(world),
    )
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(7)  # the same data on every rank
    features = [torch.randn(40, 6, generator=gen) for _ in range(3)]
    config = TrainConfig(
        width=32, depth=3, time_dim=8, T=5, batch_size=8, total_steps=6, teacher_steps=2,
        ramp_steps=2, rollout=3, ema_decay=0.0, eval_interval=0, ckpt_interval=0, seed=3,
    )  # fmt: skip
    losses: list[float] = []

    def keep(net: torch.nn.Module, step: int) -> dict[str, float]:  # called on every rank
        torch.save(net.state_dict(), Path(folder) / f"rank{rank}.pt")
        return {}

    train_amdm(
        config,
        Path(folder) / "ckpt",
        features,
        progress=False,
        eval_fn=keep,
        callback=lambda step, rec: losses.append(rec["loss"]),
    )
    torch.save(torch.tensor(losses), Path(folder) / f"losses{rank}.pt")


def test_two_processes_hold_identical_weights_after_training(tmp_path):
    mp.spawn(_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=True)
    a, b = (torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1))
    for name in a:
        assert torch.equal(a[name], b[name]), f"ranks disagree on {name}"
    # each rank drew its own batches (else this test could not tell DDP from no sync at all)
    la, lb = torch.load(tmp_path / "losses0.pt"), torch.load(tmp_path / "losses1.pt")
    assert len(la) == len(lb) == 6 and not torch.equal(la, lb)
    # rank 0 wrote the checkpoint, and its weights are the ranks' weights after training
    ckpt = load_checkpoint(tmp_path / "ckpt")
    assert ckpt.step == 6
    for name, value in ckpt.model.state_dict().items():
        assert torch.equal(value, a[name])
