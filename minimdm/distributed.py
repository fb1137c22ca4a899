"""Multi-process training on PyTorch's own engine (``torch.distributed``, DDP).

``torchrun --nproc_per_node=N -m minimdm train CONFIG`` starts N copies of the trainer and sets
``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``, ``MASTER_ADDR`` and ``MASTER_PORT`` for each. The
trainer then calls :func:`setup`, which joins the process group (``gloo`` on the CPU, ``nccl``
on GPUs, one GPU per process), and wraps its network in
:class:`~torch.nn.parallel.DistributedDataParallel`: every rank draws its own share of the
batch, and DDP averages the gradients over the ranks during ``backward``, so every rank takes
the same optimizer step and holds the same weights. Only rank 0 writes checkpoints and logs.

Without those variables (a plain ``minimdm train``) :func:`setup` does nothing and the trainer
runs in one process.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

__all__ = ["World", "setup", "teardown"]


@dataclass(frozen=True)
class World:
    """Where this process stands among the training processes."""

    rank: int = 0
    """This process's index, 0..size-1 (0 writes checkpoints and logs)."""
    size: int = 1
    """Number of processes (1: no distribution)."""
    device: str = "cpu"
    """The device this process trains on (``cuda:LOCAL_RANK`` on GPUs)."""
    owns_group: bool = False
    """True when :func:`setup` created the process group (and :func:`teardown` destroys it)."""

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def setup(device: str = "cpu") -> World:
    """Join the process group that ``torchrun`` describes in the environment, if any.

    Args:
        device: the config's device: ``"cpu"`` (backend gloo) or ``"cuda"`` (backend nccl, the
            process's GPU is ``cuda:LOCAL_RANK``).

    Returns:
        This process's :class:`World`; ``World(device=device)`` when ``WORLD_SIZE`` is unset or 1.
    """
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1 and not dist.is_initialized():
        return World(device=device)
    cuda = torch.device(device).type == "cuda"
    if cuda:
        if not torch.cuda.is_available():
            raise RuntimeError("device 'cuda' was asked for, but torch sees no CUDA GPU")
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        device = f"cuda:{local}"
    owns = not dist.is_initialized()
    if owns:
        dist.init_process_group(backend="nccl" if cuda else "gloo")
    return World(dist.get_rank(), dist.get_world_size(), device, owns)


def teardown(world: World) -> None:
    """Leave the process group if :func:`setup` created it."""
    if world.owns_group and dist.is_initialized():
        dist.destroy_process_group()
