"""What every benchmark prints beside its numbers: the hardware, and a JSON-line printer."""

from __future__ import annotations

import json
import os
import platform
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from anywhere without installing


def hardware(device: str = "cpu") -> dict:
    """Machine facts for a benchmark line: CPU, threads, torch version and the GPU if used."""
    info = {
        "torch": torch.__version__,
        "device": device,
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "threads": torch.get_num_threads(),
    }
    if str(device).startswith("cuda"):
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def sync(device: str) -> None:
    """Wait for the GPU so that wall-clock times are real."""
    if str(device).startswith("cuda"):
        torch.cuda.synchronize(device)


def emit(record: dict, file=None, quiet: bool = False) -> None:
    """Print one JSON line (unless ``quiet``) and append it to ``file`` if given."""
    line = json.dumps(record)
    if not quiet:
        print(line, flush=True)
    if file is not None:
        with open(file, "a") as f:
            f.write(line + "\n")
