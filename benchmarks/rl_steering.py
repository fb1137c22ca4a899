"""Chapter 7: RL steering of A-MDM against the book's other controls (A-MDM §6-7.4, Figs. 11-13).

Prints one JSON line per measurement (and appends it to ``--out``). Not a test.

* ``curves`` (Fig. 11): learning curves on target reaching for A-MDM steered by residuals and
  the MVAE-style baseline steered through its latent, same task, reward, PPO settings and
  budget, over seeds; two variants of the shipped design: with a motion penalty, and one
  residual over all 255 features; and on joystick control, the policy observing the frame's
  root against the whole frame (:data:`CURVE_RUNS`). Each curve's rollouts (return, the task's
  reward, bone error and foot sliding per frame) go to ``--curves`` for the chapter's plot.
* ``target``: the same targets for the shipped policy (``rl_target``), chapter 5's beam search
  and chapter 6's inpainting along the straight line to the goal: success within 15 cm, time to
  target, foot sliding, bone error, acceleration and the share of frames stepping backwards.
* ``joystick``: heading and speed errors against preset commands, the shipped policy
  (``rl_joystick``) against the unsteered base model and a hand-written proportional
  controller on the same residual.
* ``path`` (Fig. 13): deviation from procedural paths, the shipped policy (``rl_path``)
  against inpainting the same path.
* ``diversity`` (Fig. 12): runs from one start through the same sequence of targets; how far
  apart their root paths are.
* ``speed``: policy + A-MDM in ms/frame at batch 1 on one thread, with the base model alone.

Everything is held out from the policies' training. The characters start from frame 20 of the
corpus's held-out walk and run takes (character i from take i mod 6), at the origin facing +x,
every method from the same starts; the targets, commands and paths are drawn with
``HELD_OUT_SEED``, which no training run uses (training draws its goals from torch generators
seeded 0-2). Seeds change the models' noise (and the beam's candidates). The diversity and speed
runs start from one take, ``dataset-1_walk_normal_001``.

    python benchmarks/rl_steering.py                        # everything but the curves
    python benchmarks/rl_steering.py --only curves          # about 70 min on 2 cores
    # or as two processes of one thread, half the curves each (about 11 min per curve):
    python benchmarks/rl_steering.py --only curves --threads 1 \
        --curve amdm_residual_root mvae_latent joystick_observe_root
    python benchmarks/rl_steering.py --only curves --threads 1 \
        --curve amdm_residual_root_penalty amdm_residual_all joystick_observe_frame
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from common import ROOT, emit, hardware

import minimdm
from minimdm import control as C
from minimdm.amdm import evaluation
from minimdm.motion import metrics
from minimdm.motion.skeleton import wrap_angle
from minimdm.rl import load_steering, procedural_paths
from minimdm.rl.rollout import steer
from minimdm.rl.train import load_config, train_policy

START = ("dataset-1_walk_normal_001", 20)
START_CONTENTS = ("walk", "run")
"""The held-out takes the task runs start from (frame 20 of each)."""
HELD_OUT_SEED = 7919
"""Seeds the benchmark's targets, commands and paths."""
RESULTS = ROOT / "benchmarks" / "results"


def mean_ci(values) -> dict:
    """Mean and 95% t-interval half-width over seeds."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {"mean": None, "ci95": None, "n": 0}
    t = {1: float("nan"), 2: 12.71, 3: 4.30, 4: 3.18, 5: 2.78}.get(len(v), 2.0)
    half = t * v.std(ddof=1) / math.sqrt(len(v)) if len(v) > 1 else None
    return {
        "mean": round(float(v.mean()), 4),
        "ci95": None if half is None else round(half, 4),
        "n": int(len(v)),
    }


def backward_share(features: torch.Tensor, fps: float, threshold: float = 0.1) -> float:
    """Share of frames whose root moves backwards (heading-frame forward velocity below
    ``-threshold`` m/s)."""
    return float((features[..., 0] * fps < -threshold).float().mean())


def quality(pos: torch.Tensor, feats: torch.Tensor, lengths, skeleton, offsets, fps) -> dict:
    """FS (cm/frame), Bone.Err (cm), Jnt.Accel (cm/frame^2), backward share and the root's
    planar speed (m/s), averaged over the characters, each over its first ``lengths[i]``
    frames."""
    ref = metrics.skeleton_bone_lengths(skeleton.offsets, skeleton.parents)
    rows = []
    for i, n in enumerate(lengths):
        n = max(int(n), 4)
        p = pos[i : i + 1, :n]
        rows.append(
            [
                metrics.foot_sliding(p, skeleton.foot_indices, foot_offset=offsets),
                metrics.bone_length_error(p, skeleton.parents, ref),
                metrics.joint_acceleration(p),
                backward_share(feats[i, :n], fps),
                float((p[0, 1:, 0, :2] - p[0, :-1, 0, :2]).norm(dim=-1).mean()) * fps,
            ]
        )
    keys = ("FS", "Bone.Err", "Jnt.Accel", "backward", "speed_mps")
    return dict(zip(keys, np.mean(rows, axis=0).tolist(), strict=True))


def summarize(bench: str, method: str, per_seed: list[dict], extra: dict | None = None) -> None:
    keys = per_seed[0].keys()
    row = {"bench": bench, "method": method, "seeds": len(per_seed), "tag": TAG, **(extra or {})}
    row.update({k: mean_ci([s[k] for s in per_seed]) for k in keys})
    emit(row, OUT)


# --------------------------------------------------------------------------- curves


CURVE_RUNS = {
    # -- target reaching (configs/rl_target.yaml, changed as given) --
    # the shipped design: a tied residual on the root, the policy observing the whole frame
    "amdm_residual_root": {},
    # Fig. 11's baseline: the MVAE-style model steered through its latent, same reward
    "mvae_latent": {"base": "mvae"},
    # the same with a motion penalty (0.1 per cm of bone error + foot sliding per frame)
    "amdm_residual_root_penalty": {"motion_penalty": 0.1},
    # one residual over all 255 features, on the 4 noisiest steps (w^t = 1)
    "amdm_residual_all": {
        "features": "all",
        "n_levels": 4,
        "anneal": "none",
        "residual_scale": 1.0,
    },
    # -- joystick control (configs/rl_joystick.yaml): what the policy observes --
    # the shipped design: the frame's root velocity and yaw rate, and the command
    "joystick_observe_root": {"task": "joystick"},
    # the paper's: the whole frame (255 numbers), and the command
    "joystick_observe_frame": {"task": "joystick", "observe": "frame"},
}


def _tail_mean(history: list[dict], key: str) -> float:
    """Mean of ``key`` over the last 20% of the logged rollouts (NaN if never logged)."""
    n = max(1, len(history) // 5)
    v = [h[key] for h in history[-n:] if h.get(key) is not None]
    return float(np.mean(v)) if v else float("nan")


def curves(args) -> None:
    import dataclasses

    for name, run in CURVE_RUNS.items():
        if args.curve and name not in args.curve:
            continue
        change = {k: v for k, v in run.items() if k != "task"}
        task = run.get("task", "target")
        base_cfg = load_config(ROOT / "configs" / f"rl_{task}.yaml")
        finals = []
        for seed in range(args.seeds):
            cfg = dataclasses.replace(base_cfg, total_steps=args.budget, seed=seed, **change)
            out = Path(tempfile.mkdtemp(prefix=f"rl_curve_{name}_s{seed}_"))  # not kept
            try:
                r = train_policy(cfg, out, progress=False, num_threads=args.threads)
            except ValueError as e:  # PPO diverged: SB3's Gaussian got a NaN mean
                emit({"curve": name, "seed": seed, "tag": TAG, "diverged": str(e).splitlines()[0]},
                     CURVES)  # fmt: skip
                finals.append({"diverged": 1.0})
                continue
            for row in r.history:
                emit({"curve": name, "seed": seed, "tag": TAG, **row}, CURVES, quiet=True)
            finals.append(
                {
                    "final_return": _tail_mean(r.history, "return_mean"),
                    "final_task_reward_per_frame": _tail_mean(r.history, "task_reward"),
                    "final_bone_cm": _tail_mean(r.history, "bone_cm"),
                    "final_slide_cm": _tail_mean(r.history, "slide_cm"),
                    "seconds": r.seconds,
                    "diverged": 0.0,
                }
            )
        keys = dict.fromkeys(k for f in finals for k in f)
        finals = [{k: f.get(k, float("nan")) for k in keys} for f in finals]
        summarize("curves", name, finals, {"budget": args.budget, "task": task, **change})


# --------------------------------------------------------------------------- target reaching


def fixed_goals(n: int, seed: int = 0) -> torch.Tensor:
    """``n`` targets uniform in the 20 m x 20 m square around the origin, at least 1 m away."""
    rng = np.random.default_rng(seed)
    g = rng.uniform(-10, 10, size=(4 * n, 2))
    g = g[np.linalg.norm(g, axis=1) > 1.0][:n]
    return torch.tensor(g, dtype=torch.float32)


def first_hit(hit: torch.Tensor) -> torch.Tensor:
    """(N,) 1-based frame of the first True per row of (N, F), -1 if none."""
    any_ = hit.any(dim=1)
    idx = hit.float().argmax(dim=1) + 1
    return torch.where(any_, idx, torch.full_like(idx, -1))


def target(amdm, starts, ctx, args) -> None:
    goals = fixed_goals(args.targets, HELD_OUT_SEED)
    N, F = len(goals), args.max_frames
    pol = load_steering(args.rl_target)
    fps = pol.cm.fps
    walk_speed = ctx["walk_speed"]
    res = {"rl_policy": [], "beam_search": [], "inpaint_line": []}
    for seed in range(args.seeds):
        t0 = time.perf_counter()
        m = steer(
            pol, F, N, starts=starts, setup=lambda env: env.task.set_targets(goals), seed=seed
        )
        sec = time.perf_counter() - t0
        done = first_hit(m.info["hit"])
        res["rl_policy"].append(_target_row(m.positions, m.features, done, F, ctx, sec, fps))

        g = torch.Generator().manual_seed(seed)
        t0 = time.perf_counter()
        b = C.beam_search(
            amdm,
            starts[torch.arange(N) % len(starts)],
            C.target_score(goals.double()),
            F,
            pool=args.pool,
            generator=g,
            stop_fn=C.reached(goals.double()),
        )
        sec = time.perf_counter() - t0
        done = b.info["done_at"]
        res["beam_search"].append(_target_row(b.positions, b.features, done, F, ctx, sec, fps))

        rows = []
        t0 = time.perf_counter()
        for i in range(N):  # each line has its own length (time at walking speed)
            path = C.polyline_path(
                torch.stack([torch.zeros(2), goals[i]]).double(), walk_speed, fps
            )
            con = C.root_path_targets(amdm.layout, path)
            g = torch.Generator().manual_seed(seed * 1000 + i)
            s0 = starts[i % len(starts)]
            mi = C.inpaint(amdm, s0, con.targets, con.mask, g, start_pose=con.start_pose)
            d = (mi.root_xy[-1] - goals[i]).norm()
            n = mi.n_frames if d < 0.15 else -1
            rows.append(
                _target_row(
                    mi.positions[None],
                    mi.features[None],
                    torch.tensor([n]),
                    mi.n_frames,
                    ctx,
                    0.0,
                    fps,
                )
            )
        sec = time.perf_counter() - t0
        avg = {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]}
        avg["success_rate"] = float(np.mean([r["success_rate"] for r in rows]))
        avg["seconds"] = sec
        res["inpaint_line"].append(avg)
    for name, per_seed in res.items():
        summarize(
            "target",
            name,
            per_seed,
            {
                "targets": N,
                "max_frames": F,
                "radius_m": 0.15,
                "pool": args.pool,
                "walk_speed_mps": round(walk_speed, 2),
            },
        )


def _target_row(pos, feats, done, F, ctx, seconds, fps) -> dict:
    ok = done > 0
    lengths = [int(d) if d > 0 else F for d in done]
    q = quality(pos, feats, lengths, ctx["skeleton"], ctx["offsets"], fps)
    return {
        "success_rate": float(ok.float().mean()),
        "seconds_to_target": float(done[ok].float().mean() / fps) if ok.any() else float("nan"),
        **q,
        "seconds": seconds,
    }


# --------------------------------------------------------------------------- joystick


def commands(n: int, frames: int, seed: int = 0, speed=(0.5, 2.5)):
    """Preset joystick commands (n, frames): direction redrawn every 120 frames, speed every 240."""
    rng = np.random.default_rng(seed)
    k_dir, k_speed = frames // 120 + 1, frames // 240 + 1
    d = rng.uniform(0, 2 * math.pi, size=(n, k_dir))
    v = rng.uniform(*speed, size=(n, k_speed))
    f = np.arange(frames)
    return torch.tensor(d[:, f // 120], dtype=torch.float32), torch.tensor(
        v[:, f // 240], dtype=torch.float32
    )


def proportional_joystick(
    steering, k_heading: float = 2.0, k_speed: float = 1.0, k_turn: float = 0.0
):
    """A hand-written controller on the joystick policy's own actions, a baseline: the yaw-rate
    residual turns towards the command in proportion to the heading error (radians), the
    forward-velocity residual pushes the forward speed towards the commanded one (times the
    cosine of the error: no push while facing away). The gains are the best of (2, 1), (5, 2),
    (10, 3) on other commands; the lateral residual stays 0. ``k_turn`` > 0 makes it a PD
    controller: the yaw residual also pushes against the current frame's yaw rate (radians per
    second) with that gain, to damp a turn (``benchmarks/rl_joystick_study.py --controllers``
    ranks such gains; the benchmark's baseline is the proportional one)."""
    features = steering.steerer.features
    if features != "root":
        raise ValueError(f"the controller needs root residuals, got features={features!r}")
    yaw_col = steering.cm.layout.yaw_rate.start

    def act(env) -> torch.Tensor:
        task, ch = env.task, env.ch
        err = wrap_angle(task.goal_heading - ch.heading, include_pi=False)
        facing = torch.stack([torch.cos(ch.heading), torch.sin(ch.heading)], -1)
        forward = (ch.velocity * facing).sum(-1)
        a = torch.zeros(env.num_envs, env.single_action_space.shape[0])
        a[:, 2] = k_heading * err  # (forward, left, yaw)
        if k_turn:
            turn = steering.cm.denormalize(env.x)[:, yaw_col].float().cpu() * steering.cm.fps
            a[:, 2] -= k_turn * turn
        a[:, 0] = k_speed * (task.goal_speed * torch.cos(err).clamp(min=0) - forward)
        return a

    return act


def joystick(starts, ctx, args) -> None:
    pol = load_steering(args.rl_joystick)
    N, F = args.commands, 480
    heading, speed = commands(N, F + 1, HELD_OUT_SEED)
    fps = pol.cm.fps
    runs = {
        "rl_policy": {},
        "unsteered": {"zero_policy": True},
        "p_controller": {"controller": proportional_joystick(pol)},
    }
    res = {name: [] for name in runs}
    for seed in range(args.seeds):
        for name, how in runs.items():
            m = steer(
                pol,
                F,
                N,
                starts=starts,
                setup=lambda env: env.task.preset(heading, speed),
                seed=seed,
                **how,
            )
            signed = m.info["heading_error"] * 180 / math.pi  # heading - command, + = left
            he = signed.abs()
            se = m.info["speed_error"].abs()
            since = torch.arange(F) % 120  # frames since the last command change
            settled = since >= 60
            res[name].append(
                {
                    "heading_error_deg": float(he.mean()),
                    "heading_error_settled_deg": float(he[:, settled].mean()),
                    "heading_error_settled_signed_deg": float(signed[:, settled].mean()),
                    "speed_error_settled_signed_mps": float(
                        m.info["speed_error"][:, settled].mean()
                    ),
                    "speed_error_mps": float(se.mean()),
                    "speed_error_settled_mps": float(se[:, settled].mean()),
                    "reward_eq8": float(m.reward.mean()),
                    **quality(
                        m.positions, m.features, [F] * N, ctx["skeleton"], ctx["offsets"], fps
                    ),
                }
            )
    for name, per_seed in res.items():
        summarize(
            "joystick", name, per_seed, {"commands": N, "frames": F, "speed_range": [0.5, 2.5]}
        )


# --------------------------------------------------------------------------- path following


def path(amdm, starts, ctx, args) -> None:
    pol = load_steering(args.rl_path)
    N, F = args.paths, 450
    paths = procedural_paths(
        N, F, torch.Generator().manual_seed(HELD_OUT_SEED), pol.task.speed_range, pol.task.turn_max
    )  # (N, F + 1, 2) from the origin facing +x
    fps = pol.cm.fps
    res = {"rl_policy": [], "inpaint_path": []}
    for seed in range(args.seeds):
        m = steer(pol, F, N, starts=starts, setup=lambda env: env.task.set_paths(paths), seed=seed)
        dev = m.info["deviation"]
        res["rl_policy"].append(
            {
                "deviation_mean_m": float(dev.mean()),
                "deviation_max_m": float(dev.max(1).values.mean()),
                "held_within_0.5m": float((dev.max(1).values < 0.5).float().mean()),
                **quality(m.positions, m.features, [F] * N, ctx["skeleton"], ctx["offsets"], fps),
            }
        )
        rows = []
        for i in range(N):
            con = C.root_path_targets(amdm.layout, paths[i].double())
            g = torch.Generator().manual_seed(seed * 1000 + i)
            s0 = starts[i % len(starts)]
            mi = C.inpaint(amdm, s0, con.targets, con.mask, g, start_pose=con.start_pose)
            d = (mi.root_xy - paths[i, 1:]).norm(dim=-1)
            rows.append(
                {
                    "deviation_mean_m": float(d.mean()),
                    "deviation_max_m": float(d.max()),
                    "held_within_0.5m": float(d.max() < 0.5),
                    **quality(
                        mi.positions[None],
                        mi.features[None],
                        [F],
                        ctx["skeleton"],
                        ctx["offsets"],
                        fps,
                    ),
                }
            )
        res["inpaint_path"].append({k: float(np.mean([r[k] for r in rows])) for k in rows[0]})
    for name, per_seed in res.items():
        summarize("path", name, per_seed, {"paths": N, "frames": F})


# --------------------------------------------------------------------------- diversity


def diversity(start, args) -> None:
    pol = load_steering(args.rl_target)
    seq = torch.tensor([[4.0, 3.0], [0.0, 7.0], [-5.0, 4.0], [-3.0, -3.0]])
    runs, F = args.diversity_runs, 600
    per_seed = []
    for seed in range(args.seeds):
        # one batch of runs from the same start; the model's noise makes them differ
        m = steer(
            pol,
            F,
            runs,
            starts=start[None],
            setup=lambda env: env.task.set_targets(seq.expand(runs, -1, -1)),
            seed=seed,
        )
        xy = m.root_xy  # (R, F, 2)
        pair = (xy[:, None] - xy[None]).norm(dim=-1).mean(-1)  # (R, R)
        reached = m.info["hit"].sum(1).float()
        per_seed.append(
            {
                "pairwise_path_distance_m": float(pair.sum() / (runs * (runs - 1))),
                "targets_reached_mean": float(reached.clamp(max=len(seq)).mean()),
            }
        )
    summarize(
        "diversity", "rl_policy", per_seed, {"runs": runs, "frames": F, "targets": seq.tolist()}
    )


# --------------------------------------------------------------------------- speed


def speed(start, args) -> None:
    torch.set_num_threads(1)
    for name in ("rl_target", "rl_joystick", "rl_path"):
        pol = load_steering(getattr(args, name))
        for label, zero in ((f"{name}+amdm", False), ("amdm_alone", True)):
            times = []
            for rep in range(args.repeats + 1):
                t0 = time.perf_counter()
                steer(pol, args.speed_frames, 1, starts=start[None], seed=rep, zero_policy=zero)
                if rep:  # the first run warms up
                    times.append((time.perf_counter() - t0) / args.speed_frames * 1000)
            emit(
                {
                    "bench": "speed",
                    "method": label,
                    "tag": TAG,
                    "batch": 1,
                    "threads": 1,
                    "ms_per_frame": mean_ci(times),
                    "fps": round(1000 / float(np.mean(times)), 1),
                },
                OUT,
            )


def main() -> None:
    global OUT, CURVES, TAG
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--only",
        nargs="+",
        default=["target", "joystick", "path", "diversity", "speed"],
        choices=["curves", "target", "joystick", "path", "diversity", "speed"],
    )
    p.add_argument("--rl-target", default="rl_target")
    p.add_argument("--rl-joystick", default="rl_joystick")
    p.add_argument("--rl-path", default="rl_path")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--targets", type=int, default=16)
    p.add_argument("--max-frames", type=int, default=450)
    p.add_argument("--pool", type=int, default=32, help="beam search candidates (chapter 5)")
    p.add_argument("--commands", type=int, default=8)
    p.add_argument("--paths", type=int, default=8)
    p.add_argument("--diversity-runs", type=int, default=8)
    p.add_argument("--budget", type=int, default=300_000, help="environment steps per curve")
    p.add_argument("--curve", nargs="*", default=None, help="only these curves (default: all)")
    p.add_argument("--speed-frames", type=int, default=60)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default=str(RESULTS / "rl_steering.jsonl"))
    p.add_argument("--tag", default=None, help="a name for the rows (e.g. the policies' round)")
    p.add_argument("--curves", default=str(RESULTS / "rl_curves.jsonl"))
    args = p.parse_args()
    OUT, CURVES, TAG = args.out, args.curves, args.tag
    torch.set_num_threads(args.threads)
    emit({"bench": "config", **vars(args), "held_out_seed": HELD_OUT_SEED, **hardware()}, OUT)
    amdm_ckpt = minimdm.pretrained("amdm")
    amdm = C.Sampler.load(amdm_ckpt)
    start = evaluation.initial_state(amdm_ckpt, *START).features  # (D,)
    test = evaluation.checkpoint_clips(amdm_ckpt, split="test")
    held = [c.name for c in test if c.labels["content"] in START_CONTENTS]
    starts = torch.stack([evaluation.initial_state(amdm_ckpt, n, 20).features for n in held])
    skeleton = test[START[0]].skeleton
    walks = [c for c in test if c.labels["content"] == "walk"]
    walk_pos = torch.cat([torch.as_tensor(c.positions) for c in walks])
    root_speed = (
        torch.cat(
            [torch.as_tensor(c.positions[1:, 0, :2] - c.positions[:-1, 0, :2]) for c in walks]
        ).norm(dim=-1)
        * amdm.fps
    )
    ctx = {
        "skeleton": skeleton,
        "offsets": metrics.foot_contact_offsets(walk_pos, skeleton.foot_indices),
        "walk_speed": float(root_speed.median()),
    }
    if "curves" in args.only:
        curves(args)
    if "target" in args.only:
        target(amdm, starts, ctx, args)
    if "joystick" in args.only:
        joystick(starts, ctx, args)
    if "path" in args.only:
        path(amdm, starts, ctx, args)
    if "diversity" in args.only:
        diversity(start, args)
    if "speed" in args.only:
        speed(start, args)


OUT = CURVES = TAG = None

if __name__ == "__main__":
    main()
