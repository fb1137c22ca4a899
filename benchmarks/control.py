"""Control without retraining (A-MDM §4.2-4.3, §6.1, §7.3.3): success, errors, quality, speed.

Prints one JSON line per measurement. Not a test.

* ``target_reaching``: task-oriented sampling from a fixed start at the origin towards targets
  drawn uniformly in a 20 m x 20 m square around it (§6.1), success within 15 cm, for A-MDM,
  the MVAE-style VAE and the MSE regressor under the same search. The regressor is
  deterministic, so its pool holds P copies of one candidate; it is run as is (``mse``) and as
  the Gaussian that MSE training fits, :math:`\\mathcal N(f(x), \\sigma^2)` with the per-dimension
  residual std of the regressor on the training data (``mse+gauss``).
* ``inpainting``: following a circle and a figure-eight with the root (and the head held at 90%
  of its mean height in the held-out walks, a lowered stance): trajectory error and motion
  quality (foot sliding, bone error, acceleration) against random sampling from the same start.
* ``inbetweening``: transitions from the start walk to keyframes of held-out takes of other
  contents (a run, a bow, a farewell wave, a side-step): keyframe error and smoothness against
  linear interpolation in feature space and random sampling.
* ``speed``: ms/frame of each technique for one character on the CPU.
* ``spread``: how far a model's next frames spread, given the same previous frame. From 48
  frames of the held-out locomotion takes, P = 32 next frames each; the RMS over contexts of
  their per-feature std, per feature group, in units of each feature's spread over the training
  frames. The data's row is the RMS residual of the MSE regressor on the same frames: what the
  previous frame leaves unexplained. Sampling-based control can only choose among futures that
  differ, and the root's yaw rate is what turns a character.
* ``gain``: the one-step speed gain. From every 5th frame of the held-out locomotion takes, the
  mean root speed of P = 8 drawn next frames over the recorded next frames', per content and
  in all. Below 1 a model brakes on the data's own frames; a model that holds this near the
  MSE regressor's but still slows down in a rollout slows on the frames it makes itself.

The start state is frame 20 of the held-out test take ``dataset-1_walk_normal_001`` (a normal
walk no model has seen), placed at the origin heading +x; the models are the corpus models of
chapters 3 to 6 (trained on the training takes of ``bandai-namco-1``). Bone errors are measured
against the start take's own bone lengths (the corpus has several actors):

    python benchmarks/control.py                         # target reaching and speed
    python benchmarks/control.py --only inpaint inbetween
    python benchmarks/control.py --quick                 # fewer runs
    python benchmarks/control.py --amdm /tmp/amdm --mse /tmp/mse --mvae /tmp/mvae
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from common import emit, hardware

from minimdm import control as C
from minimdm.amdm import evaluation
from minimdm.amdm.sampling import rollout
from minimdm.checkpoint import load_checkpoint
from minimdm.files import atomic_output
from minimdm.motion import metrics

START = {"bandai-namco-1": ("dataset-1_walk_normal_001", 20)}
"""The fixed start state per corpus (take, frame): a walking pose of a held-out test take, which
no model has seen, placed at the origin heading +x."""

HEAD = "Head"
"""The joint whose height the lowered-stance inpainting holds."""

KEYFRAMES = (("run", 60, 60), ("bow", 60, 45), ("bye", 60, 45), ("walk-left", 60, 30))
"""Inbetweening cases: (content of a held-out take, its keyframe frame, N frames to reach it)."""


def load(spec: str):
    """``pretrained:NAME`` (minimdm.pretrained) or a checkpoint path."""
    if spec.startswith("pretrained:"):
        import minimdm

        return minimdm.pretrained(spec.split(":", 1)[1])
    return load_checkpoint(spec)


def quality(pos: torch.Tensor, skeleton, offsets) -> dict:
    """FS (cm/frame), Bone.Err (cm), Jnt.Accel (cm/frame^2) of (K, F, J, 3) motions; bone
    lengths are ``skeleton``'s (the actor of the start take or of the data's own clip)."""
    ref = metrics.skeleton_bone_lengths(skeleton.offsets, skeleton.parents)
    fs = metrics.foot_sliding(pos, skeleton.foot_indices, foot_offset=offsets)
    return {
        "FS": round(fs, 3),
        "Bone.Err": round(metrics.bone_length_error(pos, skeleton.parents, ref), 3),
        "Jnt.Accel": round(metrics.joint_acceleration(pos), 3),
    }


# --------------------------------------------------------------------------- next-frame spread


def next_frame_spread(models: dict, mse, args) -> None:
    from minimdm.studies.locomotion import locomotion_takes

    ref = C.Sampler.load(mse)  # its normalizer: the training frames' spread, feature_scale 1
    takes = locomotion_takes(mse.config.get("corpus") or "bandai-namco-1")
    pairs = [encode_pairs(c) for c in takes]
    prev, nxt = torch.cat([p for p, _ in pairs]), torch.cat([n for _, n in pairs])  # raw features
    pick = torch.randperm(len(prev), generator=torch.Generator().manual_seed(args.seed))[:48]
    prev, nxt = prev[pick], nxt[pick]
    lay = ref.layout
    groups = {"root_vel": lay.root_vel, "yaw_rate": lay.yaw_rate, "joint_pos": lay.joint_pos,
              "joint_vel": lay.joint_vel, "joint_rot": lay.joint_rot}  # fmt: skip

    def rms(x: torch.Tensor) -> dict:  # (N, D) in units of the training spread -> per group
        return {k: round(float(x[:, g].pow(2).mean().sqrt()), 4) for k, g in groups.items()}

    with torch.no_grad():
        resid = ref.normalize(nxt) - ref.net(ref.normalize(prev))
    emit({"bench": "next_frame_spread", "model": "data (MSE residual)", "contexts": len(prev),
          **rms(resid)})  # fmt: skip
    P = 32
    for name, cm in models.items():
        g = torch.Generator().manual_seed(args.seed + 1)
        x = cm.frame(cm.normalize(prev).repeat_interleave(P, 0), g)
        x = ref.normalize(cm.denormalize(x)).view(len(prev), P, -1)
        emit({"bench": "next_frame_spread", "model": name, "contexts": len(prev), "samples": P,
              **rms(x.std(1)), "mean_error": rms(x.mean(1) - ref.normalize(nxt))})  # fmt: skip


def encode_pairs(clip, every: int = 15) -> tuple[torch.Tensor, torch.Tensor]:
    """(previous, next) raw feature frames of a take, every ``every``-th frame from frame 30."""
    from minimdm.motion.features import encode

    x = encode(clip).float()
    i = torch.arange(30, x.shape[0] - 1, every)
    return x[i], x[i + 1]


def speed_gain(models: dict, corpus: str, args) -> None:
    from minimdm.studies.locomotion import locomotion_takes

    takes = locomotion_takes(corpus)
    pairs = [encode_pairs(c, every=5) for c in takes]
    P = 8
    for name, cm in models.items():
        drawn, recorded = {}, {}
        for clip, (prev, nxt) in zip(takes, pairs, strict=True):
            g = torch.Generator().manual_seed(args.seed)
            with torch.no_grad():
                x = cm.frame(cm.normalize(prev).repeat_interleave(P, 0), g)
            x = cm.denormalize(x).view(len(prev), P, -1)
            root = cm.layout.root_vel
            content = clip.labels["content"]
            drawn.setdefault(content, []).append(x[..., root].norm(dim=-1).mean(1))  # (N,)
            recorded.setdefault(content, []).append(nxt[:, root].norm(dim=-1))

        def ratio(keys, drawn=drawn, recorded=recorded) -> float:
            a = torch.cat([t for k in keys for t in drawn[k]])
            b = torch.cat([t for k in keys for t in recorded[k]])
            return round(float(a.mean() / b.mean()), 4)

        n = sum(len(t) for v in recorded.values() for t in v)
        emit({"bench": "speed_gain", "model": name, "contexts": n, "samples": P,
              "all": ratio(list(drawn)), "by_content": {k: ratio([k]) for k in drawn}})  # fmt: skip


# --------------------------------------------------------------------------- target reaching


def wilson_interval(successes: int, n: int, z: float = 1.96) -> list[float]:
    """95% Wilson score interval of a success rate ``successes / n`` (runs are Bernoulli)."""
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [round(max(0.0, centre - half), 3), round(min(1.0, centre + half), 3)]


def stat(value: torch.Tensor, ok: torch.Tensor, digits: int) -> float | None:
    """``value`` rounded, or None when no run succeeded."""
    return round(float(value), digits) if ok.any() else None


def target_reaching(models: dict, start, args) -> None:
    rng = np.random.default_rng(args.seed)
    goals = torch.tensor(rng.uniform(-10, 10, size=(args.runs, 2)), dtype=torch.float64)
    goals = goals[goals.norm(dim=1) > 0.15]
    dist = goals.norm(dim=1)
    for name, cm in models.items():
        g = torch.Generator().manual_seed(args.seed)
        t0 = time.perf_counter()
        m = C.beam_search(
            cm, start.expand(len(goals), -1), C.target_score(goals), args.max_frames,
            pool=args.pool, horizon=args.horizon, commit=args.commit, generator=g,
            stop_fn=C.reached(goals),
        )  # fmt: skip
        seconds = time.perf_counter() - t0
        done = m.info["done_at"]
        ok = done > 0
        closest = (m.root_xy - goals[:, None].float()).norm(dim=-1).min(dim=1).values
        steps = m.root_xy.diff(dim=1).norm(dim=-1)
        length = torch.stack([steps[i, : (int(done[i]) if ok[i] else steps.shape[1]) - 1].sum()
                              for i in range(len(goals))])  # fmt: skip
        emit({
            "bench": "target_reaching", "model": name, "runs": len(goals), "pool": args.pool,
            "horizon": args.horizon, "commit": args.commit, "max_frames": args.max_frames,
            "radius_m": 0.15,
            "success_rate": round(float(ok.double().mean()), 3),
            "successes": int(ok.sum()),
            "success_ci95": wilson_interval(int(ok.sum()), len(goals)),
            "frames_to_target_mean": stat(done[ok].double().mean(), ok, 1),
            "frames_to_target_median": stat(done[ok].double().median(), ok, 1),
            "path_over_distance": stat((length[ok] / dist[ok]).mean(), ok, 2),
            "target_distance_mean_m": round(float(dist.mean()), 2),
            "closest_approach_median_m": round(float(closest.median()), 2),
            "seconds": round(seconds, 1),
        })  # fmt: skip
        if args.save_paths:
            with atomic_output(f"{args.save_paths}_{name}.npy") as tmp:
                np.save(tmp, m.root_xy.numpy())


# --------------------------------------------------------------------------- inpainting


def inpainting(label, cm, start, skeleton, offsets, head_height, args) -> None:
    K, F = args.samples, args.inpaint_frames
    head_j = cm.layout.joint_names.index(HEAD)
    paths = {
        "circle_r2": C.circle_path(2.0, 1.0, F, cm.fps),
        "figure_eight_r1.5": C.figure_eight_path(1.5, 1.0, F, cm.fps),
    }
    for pname, path in paths.items():
        root = C.root_path_targets(cm.layout, path)
        head = C.joint_height_targets(cm.layout, HEAD, torch.full((F,), head_height))
        runs = {
            "inpaint_root": (root, -1),
            "inpaint_root_soft": (root, cm.schedule.T // 4),
            "inpaint_root_head": (root | head, -1),
        }
        g = torch.Generator().manual_seed(args.seed)
        free = rollout(
            cm.net,
            start[None],
            F,
            K,
            generator=g,
            normalizer=cm.normalizer,
            schedule=cm.schedule,
            clip_x0=cm.settings.clip_x0,
            start_pose=dict(xy=root.start_pose.xy, heading=root.start_pose.heading),
        )
        results = {"random_sampling": free.positions[0]}
        for rname, (con, t_stop) in runs.items():
            g = torch.Generator().manual_seed(args.seed)
            m = C.inpaint(cm, start.expand(K, -1), con.targets, con.mask, g,
                          start_pose=con.start_pose, t_stop=t_stop)  # fmt: skip
            results[rname] = m.positions
        for rname, pos in results.items():
            err = (pos[..., 0, :2] - path[1:]).norm(dim=-1)  # (K, F)
            rec = {
                "bench": "inpainting", "model": label, "path": pname, "method": rname, "samples": K,
                "frames": F, "root_err_cm_mean": round(float(err.mean() * 100), 2),
                "root_err_cm_max": round(float(err.max() * 100), 2),
                "head_height_m": round(float(pos[..., head_j, 2].mean()), 3),
                "head_target_m": round(head_height, 3) if rname == "inpaint_root_head" else None,
                **quality(pos, skeleton, offsets),
            }  # fmt: skip
            emit(rec)


# --------------------------------------------------------------------------- inbetweening


def inbetweening(label, cm, start, test, skeleton, offsets, args) -> None:
    K = args.samples
    pos_slice = cm.layout.joint_pos
    J = cm.layout.n_joints
    for content, fb, N in KEYFRAMES:
        take = next(c for c in test if c.labels["content"] == content)  # first held-out take
        key = C.clip_frame(take, fb, cm.layout)
        g = torch.Generator().manual_seed(args.seed)
        m = C.inbetween(cm, start.expand(K, -1), key, N, g)
        lerp = C.lerp_inbetween(cm, start, key, N)
        g = torch.Generator().manual_seed(args.seed)
        free = rollout(cm.net, start[None], N, K, generator=g, normalizer=cm.normalizer,
                       schedule=cm.schedule, clip_x0=cm.settings.clip_x0)  # fmt: skip
        for method, feats, pos in [
            ("inbetween_eq5", m.features, m.positions),
            ("linear_interpolation", lerp.features[None], lerp.positions[None]),
            ("random_sampling", free.features[0], free.positions[0]),
        ]:
            err = (feats[:, -1, pos_slice] - key[pos_slice]).unflatten(-1, (J, 3)).norm(dim=-1)
            acc = pos[:, 2:] - 2 * pos[:, 1:-1] + pos[:, :-2]  # (K, N-2, J, 3)
            emit({
                "bench": "inbetweening", "model": label, "from": args.start,
                "to": f"{take.name}@{fb}", "content": content, "N": N,
                "method": method, "samples": int(feats.shape[0]),
                "keyframe_err_cm": round(float(err.mean() * 100), 2),
                "keyframe_err_cm_max": round(float(err.mean(-1).max() * 100), 2),
                "root_vel_err_cm": round(float((feats[:, -1, :2] - key[:2]).norm(dim=-1).mean()
                                               * 100), 2),
                "max_Jnt.Accel": round(float(acc.norm(dim=-1).mean(-1).max() * 100), 3),
                **quality(pos, skeleton, offsets),
            })  # fmt: skip


# --------------------------------------------------------------------------- speed


def speed(cm, start, args) -> None:
    F = args.speed_frames
    goal = torch.tensor([3.0, 3.0])
    path = C.circle_path(2.0, 1.0, F, cm.fps)
    con = C.root_path_targets(cm.layout, path)
    key = start.clone()
    cases = {
        "rollout": lambda g: rollout(cm.net, start[None], F, 1, generator=g,
                                     normalizer=cm.normalizer, schedule=cm.schedule,
                                     clip_x0=cm.settings.clip_x0),
        "beam_search_P32_H1": lambda g: C.beam_search(cm, start, C.target_score(goal), F,
                                                      pool=32, horizon=1, generator=g),
        "beam_search_P100_H1": lambda g: C.beam_search(cm, start, C.target_score(goal), F,
                                                       pool=100, horizon=1, generator=g),
        "beam_search_P16_H4": lambda g: C.beam_search(cm, start, C.target_score(goal), F,
                                                      pool=16, horizon=4, generator=g),
        "inpaint_root_path": lambda g: C.inpaint(cm, start, con.targets, con.mask, g,
                                                 start_pose=con.start_pose),
        "inbetween": lambda g: C.inbetween(cm, start, key, F, g),
    }  # fmt: skip
    for name, fn in cases.items():
        times = []
        for r in range(args.repeats):
            t0 = time.perf_counter()
            fn(torch.Generator().manual_seed(r))
            times.append((time.perf_counter() - t0) / F * 1000)
        emit({"bench": "speed", "technique": name, "frames": F, "batch": 1,
              "denoising_steps": cm.schedule.T, "ms_per_frame_min": round(min(times), 2),
              "ms_per_frame_median": round(float(np.median(times)), 2), **hardware()})  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--amdm", default="pretrained:amdm")
    p.add_argument("--mvae", default="pretrained:mvae")
    p.add_argument("--mse", default="pretrained:mse")
    p.add_argument("--extra", nargs="*", default=[], metavar="NAME=PATH",
                   help="more models (diffusion ones also inpaint and inbetween)")  # fmt: skip
    p.add_argument("--only", nargs="+", default=["target", "speed"],
                   choices=["target", "inpaint", "inbetween", "speed", "spread",
                            "gain"])  # fmt: skip
    p.add_argument(
        "--start",
        default=None,
        metavar="TAKE@FRAME",
        help="start state (default: START of the A-MDM checkpoint's corpus)",
    )
    p.add_argument("--runs", type=int, default=32, help="target-reaching runs per model")
    p.add_argument(
        "--no-baselines",
        action="store_true",
        help="spread and target: score --amdm and --extra only (a study's guard)",
    )
    p.add_argument("--pool", type=int, default=32, help="P (the paper: 100)")
    p.add_argument("--horizon", type=int, default=1, help="H (the paper: 1)")
    p.add_argument(
        "--commit",
        type=int,
        default=1,
        help="frames of the best future kept before searching again (the paper: 1)",
    )
    p.add_argument("--max-frames", type=int, default=450, help="frames before a run fails")
    p.add_argument("--samples", type=int, default=8, help="samples per inpainting case")
    p.add_argument("--inpaint-frames", type=int, default=240)
    p.add_argument("--speed-frames", type=int, default=30)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--save-paths", default=None, help="save root paths to PREFIX_<model>.npy")
    p.add_argument("--quick", action="store_true", help="16 runs, 300 frames, 4 samples")
    args = p.parse_args()
    if args.quick:
        args.runs, args.max_frames, args.samples = 16, 300, 4
        args.inpaint_frames, args.repeats = 120, 2
    torch.set_num_threads(args.threads)
    amdm_ckpt = load(args.amdm)
    corpus = amdm_ckpt.config.get("corpus") or "deepmimic"
    editing = {"inpaint", "inbetween"} & set(args.only)
    if editing and amdm_ckpt.config.get("split") != "train":
        p.error(f"--only {' '.join(sorted(editing))} starts from and heads for held-out takes: "
                f"--amdm must be trained on a corpus's 'train' split, got {corpus!r}")  # fmt: skip
    if args.start is None:
        if corpus not in START:
            p.error(f"no default start state for corpus {corpus!r}: pass --start TAKE@FRAME")
        args.start = "@".join(map(str, START[corpus]))
    take, frame = args.start.rsplit("@", 1)
    amdm = C.Sampler.load(amdm_ckpt)
    start = evaluation.initial_state(amdm_ckpt, take, int(frame)).features  # (D,)
    emit({"bench": "config", **vars(args), "corpus": corpus, **hardware()})
    extras = {}
    for item in args.extra:
        name, spec = item.split("=", 1)
        extras[name] = C.Sampler.load(load(spec))
    if {"target", "spread", "gain"} & set(args.only):
        models = {"amdm": amdm, "mvae": C.Sampler.load(load(args.mvae))}
        mse = load(args.mse)
        models["mse"] = C.Sampler.load(mse)
        models["mse+gauss"] = C.Sampler.load(
            mse, noise=C.regressor_noise(mse, evaluation.checkpoint_clips(mse))
        )
        models.update(extras)
        if args.no_baselines:
            models = {k: v for k, v in models.items() if k == "amdm" or k in extras}
        if "spread" in args.only:
            next_frame_spread(models, mse, args)
        if "gain" in args.only:
            speed_gain(models, corpus, args)
        if "target" in args.only:
            target_reaching(models, start, args)
    if editing:
        test = evaluation.checkpoint_clips(amdm_ckpt, split="test")  # the held-out takes
        skeleton = test[take].skeleton  # the start take's actor: the reference bone lengths
        walks = [c for c in test if c.labels["content"] == "walk"]
        walk_pos = torch.cat([torch.as_tensor(c.positions) for c in walks])
        offsets = metrics.foot_contact_offsets(walk_pos, skeleton.foot_indices)
        head_height = 0.9 * float(walk_pos[:, skeleton.names.index(HEAD), 2].mean())
        for c in walks:  # the data's own row: each held-out walk against its own actor
            pos = torch.as_tensor(c.positions)[None].float()  # (1, F, J, 3)
            emit({"bench": "data_reference", "clip": c.name, **quality(pos, c.skeleton, offsets)})
        diffusion = {"amdm": amdm, **{k: v for k, v in extras.items() if v.is_diffusion}}
        for label, cm in diffusion.items():
            if "inpaint" in args.only:
                inpainting(label, cm, start, skeleton, offsets, head_height, args)
            if "inbetween" in args.only:
                inbetweening(label, cm, start, test, skeleton, offsets, args)
    if "speed" in args.only:
        speed(amdm, start, args)


if __name__ == "__main__":
    main()
