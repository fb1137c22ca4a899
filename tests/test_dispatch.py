"""The chapters' checked outputs do not depend on the CPU's SIMD kernels (issue 27).

Torch, MKL and oneDNN pick their kernels by instruction set (AVX-512, AVX2, ...), and the kernels
round differently in the last bits. A cell tagged ``nbval-check-output`` must therefore print only
what is exact by construction, or a bound it asserts (``< 1e-5: ok``); never a raw difference,
nor a number of a sampled rollout.

``make test-dispatch`` runs every chapter under the machine's own dispatch and under AVX2. This is
its cheap form for ``make test``: the from-scratch checks of three chapters, each with the cells it
needs before it, run by nbval as ``make test`` runs the chapters, under another dispatch than this
CPU's own.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
HERE = torch.backends.cpu.get_cpu_capability()  # the kernels torch picked for this CPU

pytestmark = pytest.mark.skipif(
    platform.machine().lower() not in ("x86_64", "amd64") or HERE == "DEFAULT",
    reason=f"needs an x86 CPU with SIMD kernels to switch from ({platform.machine()}, {HERE})",
)

CHECKS = {  # chapter -> how the from-scratch check cell that ends its prefix starts
    "06_inpainting_inbetweening": "cond = eps.normalize(x0)",  # eq. 4 as a hook, one frame
    "07_rl_steering": "def my_residual_hook",  # eq. 7 as a hook against rl.residual_hook
    "09_camdm": "def my_guided_x0",  # CFG with two calls against the library's batch of 2B
}

AVX2 = {
    "ATEN_CPU_CAPABILITY": "avx2",
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",
    "MKL_CBWR": "AVX2",
    "ONEDNN_MAX_CPU_ISA": "AVX2",
}
BASELINE = {  # what every x86-64 CPU runs: ATen's non-vectorised kernels, SSE4.2 in MKL
    "ATEN_CPU_CAPABILITY": "default",
    "MKL_ENABLE_INSTRUCTIONS": "SSE4_2",
    "MKL_CBWR": "SSE4_2",
    "ONEDNN_MAX_CPU_ISA": "SSE41",
}


def other_dispatch() -> dict[str, str]:
    """Settings under which torch runs other kernels than it does here by default."""
    return AVX2 if HERE == "AVX512" else BASELINE


def prefix(chapter: str, first_line: str) -> dict:
    """The chapter's notebook cut after the first code cell that starts with ``first_line``."""
    nb = json.loads((ROOT / "notebooks" / f"{chapter}.ipynb").read_text())
    ends = [
        i
        for i, c in enumerate(nb["cells"])
        if c["cell_type"] == "code" and "".join(c["source"]).startswith(first_line)
    ]
    assert ends, f"{chapter}: no code cell starts with {first_line!r}; update CHECKS"
    nb["cells"] = nb["cells"][: ends[0] + 1]
    return nb


def test_other_dispatch_runs_other_kernels():
    env = {**os.environ, **other_dispatch()}
    code = "import torch; print(torch.backends.cpu.get_cpu_capability())"
    pinned = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert pinned.returncode == 0, pinned.stderr
    assert pinned.stdout.strip() not in ("", HERE)


def test_from_scratch_checks_pass_under_another_cpu_dispatch(tmp_path):
    # The cut notebooks read ../configs, ../benchmarks and so on, as the chapters do.
    book = tmp_path / "notebooks"
    book.mkdir()
    for name in ("benchmarks", "checkpoints", "configs", "data"):
        (tmp_path / name).symlink_to(ROOT / name, target_is_directory=True)
    shutil.copy(ROOT / "notebooks" / "conftest.py", book)  # nbval's timeouts, as in `make test`
    n_cells = n_checked = 0
    for chapter, first_line in CHECKS.items():
        nb = prefix(chapter, first_line)
        code = [c for c in nb["cells"] if c["cell_type"] == "code"]
        n_cells += len(code)
        n_checked += sum("nbval-check-output" in c["metadata"].get("tags", []) for c in code)
        (book / f"{chapter}.ipynb").write_text(json.dumps(nb))
    assert n_checked >= 2 * len(CHECKS)  # each prefix ends with a check, after at least one more

    env = {**os.environ, **other_dispatch()}
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--nbval-lax"]
    cmd += ["--nbval-kernel-startup-timeout=300", str(book)]
    run = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    passed = re.search(r"(\d+) passed", run.stdout)
    assert passed and int(passed.group(1)) == n_cells, run.stdout[-2000:]
