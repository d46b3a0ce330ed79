"""One model from two rigs' data (issue 51): does its motion on each rig look like that rig's data?

    .venv/bin/python benchmarks/two_rigs.py [--second mirrored|synthetic] [--steps 3000]

The data: ../shared's ZEGGS clip (real capture, on ZEGGS' own BVH rig; speaker `zeggs`), and a second speaker on
the SMPL-X skeleton, as BEAT2 takes: `mirrored` (the default), the same clip retargeted onto SMPL-X and mirrored
left for right, a left-handed speaker of the same speech; or `synthetic`, `--synth-minutes` of synthetic speech
with rule-made gestures (`dimgestor.training.synthetic`). Each clip's last 15 s are held out. One model (`realtime`
preset, the streaming recipe) is trained on both with `--speaker-condition`: the takes are retargeted onto the ZEGGS
skeleton, and the two speakers take equal turns.

Then the model plays each speaker, and no speaker, on the same real speech that neither dataset holds (../shared's
unseen BEAT speaker, `--speech-s` s, `--seeds` seeds). Each output's poses are compared with each speaker's
training data on the training skeleton: the Frechet distance between Gaussians of their pose features (root
travel left out; z-scored by the model's statistics, projected on the data's first 16 principal components), the
wrists' mean speed, and handedness (the right wrist's mean speed over the left's). Each speaker's motion should be
nearer its own data than the other's. The motion is also written as each rig's file (`generate --speaker zeggs
--out X.bvh`, `--speaker mirrored --out X.npz`), rendered beside each rig's own data, and the filmstrips saved as
results/two_rigs_SECOND_frames.png to look at. Writes results/two_rigs_SECOND.json and a plot beside it.

`--speaker-guidance W ...` also plays each speaker with guidance on the speaker (`speaker_guided`: offline, three
network rows a step), its output pushed W times as far from the output with no speaker.

    .venv/bin/python benchmarks/two_rigs.py --plot-only benchmarks/results/two_rigs_mirrored.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = REPO.parent / "shared" / "data"
ZEGGS = SHARED / "zeggs_sample"
SPEECH = SHARED / "unseen_speech" / "4_lawrence_0_19_19.wav"
PCS = 16


def mirrored_take(path: Path) -> None:
    """A BEAT2 take mirrored left for right in place: the generic SMPL-X skeleton is symmetric about x = 0, so each
    joint's axis-angle (x, y, z) becomes (x, -y, -z) on its other side's joint, and the root's x changes sign."""
    from dimgestor import smplx

    with np.load(path) as f:
        fields = dict(f)
    poses = fields["poses"].reshape(len(fields["poses"]), 55, 3) * np.array([1.0, -1.0, -1.0], np.float32)
    other = [smplx.JOINTS.index(n.replace("left_", "@").replace("right_", "left_").replace("@", "right_"))
             for n in smplx.JOINTS]
    fields["poses"] = poses[:, other].reshape(len(poses), 165)
    fields["trans"] = fields["trans"] * np.array([-1.0, 1.0, 1.0], np.float32)
    np.savez(path, **fields)


def make_data(root: Path, second: str, minutes: float) -> None:
    """root/zeggs: the ZEGGS clip (linked). The second rig's speaker, as BEAT2 / SMPL-X takes + .wav: `mirrored`,
    the same clip retargeted onto SMPL-X and mirrored (a left-handed speaker of the same speech), or `synthetic`,
    `minutes` of synthetic speech with rule-made gestures."""
    from dimgestor.bvh import read_bvh
    from dimgestor.retarget.export import write_motion
    from dimgestor.training.synthetic import make_gesture_corpus

    (root / "zeggs").mkdir(parents=True)
    for f in sorted(ZEGGS.glob("*.bvh")) + sorted(ZEGGS.glob("*.wav")):
        (root / "zeggs" / f.name).symlink_to(f)
    (root / second).mkdir()
    if second == "mirrored":
        for bvh in sorted(ZEGGS.glob("*.bvh")):
            write_motion(root / second / f"{bvh.stem}.npz", read_bvh(bvh))
            mirrored_take(root / second / f"{bvh.stem}.npz")
            (root / second / f"{bvh.stem}.wav").symlink_to(bvh.with_suffix(".wav"))
        return
    for bvh, wav in make_gesture_corpus(root / "made", minutes, clip_s=60.0, seed=1):
        write_motion(root / second / f"{bvh.stem}.npz", read_bvh(bvh))
        shutil.copy(wav, root / second / wav.name)


def pose_columns(spec) -> np.ndarray:
    from dimgestor.features import HEADING_COLUMN, VELOCITY_COLUMNS

    return np.array([c for c in range(spec.dim) if c not in (*VELOCITY_COLUMNS, HEADING_COLUMN)])


def wrists(features: np.ndarray, bundle) -> tuple[float, float]:
    """(the two wrists' mean speed, the skeleton's units a second; the right one's over the left one's) of features
    on the training skeleton."""
    from dimgestor.bvh import forward_kinematics
    from dimgestor.features import features_to_motion

    motion = features_to_motion(features, bundle.skeleton, bundle.feature_spec, root="lock")
    p = forward_kinematics(motion)[:, [bundle.skeleton.index("LeftHand"), bundle.skeleton.index("RightHand")]]
    speed = np.linalg.norm(np.diff(p, axis=0), axis=-1).mean(axis=0) * bundle.feature_spec.fps
    return float(speed.mean()), float(speed[1] / speed[0])


def speaker_guided(bundle, audio: np.ndarray, seed: int, speaker: str, weight: float) -> np.ndarray:
    """`bundle.generate` with guidance on the speaker too (classifier-free guidance, Ho & Salimans 2022, with the
    speaker as the condition): each step's output for the speaker is pushed `weight` times as far from the output
    for the same speech with no speaker, then the audio's own guidance applies as the model's config says. Offline
    only (three network rows a step); `weight` 1 is `bundle.generate` itself."""
    import torch

    from dimgestor.model.diffusion import Diffusion, guide, motion_noise
    from dimgestor.streaming.stream import make_smoother

    model, c = bundle.model, bundle.model.config
    T = len(audio) * c.fps // c.sample_rate
    pad = max(model.samples_needed(T) - len(audio), 0)
    diffusion = Diffusion(c)
    with torch.inference_mode():
        wave = torch.from_numpy(np.concatenate([audio, np.zeros(pad, np.float32)]))[None]
        feats, _ = model.frontend(wave, model.frontend.init_state(1, wave.device))
        cond, _ = model.condition(feats.expand(2, -1, -1), speaker=torch.tensor([model.speaker_number(speaker), -1]))
        cond = cond[:, :T]  # (2, T, H): the speaker's, no speaker's
        if c.guidance != 1.0:
            cond = torch.cat([cond, torch.zeros_like(cond[:1])])  # and the null condition's
        x = motion_noise(seed, 0, T, 0, c.motion_dim, c.noise_taps)[None]
        for t, t_prev in diffusion.sampling_pairs("ddim", c.sample_steps):
            out, _ = model(x.expand(len(cond), -1, -1), t, cond)
            pushed = guide(out[:1], out[1:2], weight)
            if c.guidance != 1.0:
                pushed = guide(pushed, out[2:], c.guidance)
            eps, x0 = diffusion.split(pushed, x, t)
            x = diffusion.sample_step("ddim", x, eps, x0, t, t_prev)
    frames = x[0].float().numpy()
    smoother = make_smoother(c, "config")
    return bundle.denormalize(smoother(frames) if smoother is not None else frames)


def measure(bundle, data: Path, speakers: tuple[str, str], audio: np.ndarray, seeds: int,
            weights: tuple[float, ...] = ()) -> dict:
    from dimgestor.evaluation.metrics import frechet_distance, gaussian_stats
    from dimgestor.training.dataset import GestureDataset

    ds = GestureDataset([data / s for s in speakers], bundle.feature_spec, split="train", valid_seconds=15.0,
                        skeleton=bundle.skeleton, use_cache=False)
    cols = pose_columns(bundle.feature_spec)

    def z(f):
        return ((np.asarray(f, np.float64) - bundle.mean) / bundle.std)[:, cols]

    real = {s: np.concatenate([np.asarray(ds.clips[c].features[a:b]) for c, a, b in ds.segments
                               if ds.clip_speakers[c] == s]) for s in speakers}
    pooled = np.concatenate([z(real[s]) for s in speakers])
    centre = pooled.mean(0)
    basis = np.linalg.svd(pooled - centre, full_matrices=False)[2][:PCS].T  # (pose columns, PCS)

    def project(f):
        return (z(f) - centre) @ basis

    stats = {s: gaussian_stats(project(real[s])) for s in speakers}
    out = {"data": {s: {"seconds": round(len(real[s]) / bundle.feature_spec.fps, 1),
                        **dict(zip(("wrist_speed", "right_over_left"), np.round(wrists(real[s], bundle), 3)))}
                    for s in speakers}, "played": {}}
    runs = [(None, 1.0), *((s, 1.0) for s in speakers), *((s, w) for w in weights for s in speakers)]
    for played, weight in runs:
        bundle.model.use_speaker(played)
        gens = [bundle.generate(audio, seed=seed) if weight == 1 else speaker_guided(bundle, audio, seed, played, weight)
                for seed in range(seeds)]
        both = np.concatenate(gens)
        mu, sigma = gaussian_stats(project(both))
        speed, handed = np.mean([wrists(g, bundle) for g in gens], axis=0)
        label = (played or "none") + ("" if weight == 1 else f" x{weight:g}")
        out["played"][label] = {
            "distance_to": {s: round(float(frechet_distance(mu, sigma, *stats[s])), 2) for s in speakers},
            "wrist_speed": round(float(speed), 3), "right_over_left": round(float(handed), 3)}
        print(label, out["played"][label], flush=True)
    bundle.model.use_speaker(None)
    return out


def render_strips(run: Path, data: Path, speakers: tuple[str, str], wav: Path, folder: Path, out: Path) -> list[str]:
    """Each speaker's motion written as its rig's own file and rendered, beside a stretch of that rig's data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dimgestor_app.cli import main as cli

    strips = []
    for speaker, suffix in zip(speakers, (".bvh", ".npz")):
        made = folder / f"played_{speaker}{suffix}"
        assert cli(["generate", "--checkpoint", str(run), "--audio", str(wav), "--out", str(made), "--speaker",
                    speaker]) == 0
        own = sorted((data / speaker).glob(f"*{suffix}"))[0]
        for label, path in ((f"{speaker}'s data, on its rig", own), (f"the model playing {speaker}, on that rig", made)):
            png = folder / f"{speaker}_{path.stem}.png"
            assert cli(["render", str(path), "--out", str(png), "--start", "4", "--seconds", "6", "--panels", "6",
                        "--views", "front", "--title", label]) == 0
            strips.append((label, png))
    fig, axes = plt.subplots(len(strips), 1, figsize=(12, 2.6 * len(strips)))
    for ax, (label, png) in zip(axes, strips):
        ax.imshow(plt.imread(png))  # (each strip carries its label as its title)
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    return [label for label, _ in strips]


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    speakers, played = list(result["data"]), list(result["played"])
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    width = 0.38
    for k, s in enumerate(speakers):
        values = [result["played"][p]["distance_to"][s] for p in played]
        bars = axes[0].bar(np.arange(len(played)) + (k - 0.5) * width, values, width, label=f"to {s}'s data")
        axes[0].bar_label(bars, labels=[f"{v:.0f}" for v in values], fontsize=7)
    axes[0].set_xticks(range(len(played)), [f"plays {p}" for p in played], rotation=30, ha="right", fontsize=8)
    axes[0].set_title(f"Frechet distance of pose features ({PCS} PCs; lower = nearer)", fontsize=9)
    axes[0].legend(fontsize=8)
    labels = [f"plays {p}" for p in played] + [f"{s}'s data" for s in speakers]
    for ax, key, title in ((axes[1], "wrist_speed", "wrists' mean speed (cm/s)"),
                           (axes[2], "right_over_left", "right wrist's speed / left's")):
        values = [result["played"][p][key] for p in played] + [result["data"][s][key] for s in speakers]
        bars = ax.bar(range(len(values)), values, color=[f"C{2 + i}" for i in range(len(values))])
        ax.bar_label(bars, labels=[f"{v:.2f}" for v in values], fontsize=7)
        ax.set_xticks(range(len(values)), labels, rotation=30, ha="right", fontsize=8)
        ax.set_title(title, fontsize=9)
    for ax in axes:
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"one model, two rigs' data ({' and '.join(speakers)}), {result['setup']['steps']} steps; "
                 f"{result['code']}; {result['machine']}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--second", choices=("mirrored", "synthetic"), default="mirrored",
                    help="the second speaker, on the SMPL-X skeleton (default mirrored)")
    ap.add_argument("--steps", type=int, default=3000, help="training steps (default 3000)")
    ap.add_argument("--synth-minutes", type=float, default=3.0, help="synthetic SMPL-X takes, minutes (default 3)")
    ap.add_argument("--speech-s", type=float, default=30.0, help="unseen speech each speaker plays (default 30)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--speaker-guidance", type=float, nargs="*", default=[], metavar="W",
                    help="also play each speaker with guidance on the speaker at these weights (> 1; offline, three "
                         "network rows a step): its output pushed W times as far from no speaker's")
    ap.add_argument("--keep", type=Path, default=None, metavar="DIR", help="work here and keep it (default: a temp folder)")
    ap.add_argument("--out", type=Path, default=None, help="default: results/two_rigs_SECOND.json")
    ap.add_argument("--plot-only", type=Path, metavar="RESULTS.json", help="redraw RESULTS.png; measures nothing")
    args = ap.parse_args()
    if args.plot_only:
        plot(json.loads(args.plot_only.read_text()), args.plot_only.with_suffix(".png"))
        return 0
    if not ZEGGS.is_dir() or not SPEECH.is_file():
        raise SystemExit(f"needs ../shared/data (the ZEGGS clip and the unseen speech), not found at {SHARED}")
    from dimgestor.audio import SAMPLE_RATE, load_wav, save_wav
    from dimgestor.streaming.checkpoint import load_checkpoint
    from dimgestor_app.cli import main as cli

    speakers = ("zeggs", args.second)
    out = args.out or RESULTS / f"two_rigs_{args.second}.json"
    folder = args.keep or Path(tempfile.mkdtemp(prefix="two-rigs-"))
    folder.mkdir(parents=True, exist_ok=True)
    data, run = folder / "data", folder / "run"
    if not data.exists():
        make_data(data, args.second, args.synth_minutes)
    t0 = time.time()
    if not (run / "ckpt_latest").exists() and not any(run.glob("ckpt_*")):
        assert cli(["train", "--data", str(data / "zeggs"), "--data", str(data / args.second), "--out", str(run),
                    "--preset", "realtime", "--speaker-condition", "--max-steps", str(args.steps), "--batch-size", "8",
                    "--window-s", "5", "--valid-seconds", "15", "--valid-every", "0", "--no-augment", "--no-mirror",
                    "--speeds", "", "--no-arm-mix", "--no-progress", "--threads", str(args.threads),
                    "--cache-dir", str(folder / "cache")]) == 0
    train_s = time.time() - t0
    import torch

    torch.set_num_threads(args.threads)
    bundle = load_checkpoint(run)
    audio = load_wav(SPEECH, SAMPLE_RATE)[: int(args.speech_s * SAMPLE_RATE)]
    wav = folder / "speech.wav"
    save_wav(wav, audio, SAMPLE_RATE)
    result = {"what": "one model trained on two rigs' data with the speaker condition: each speaker's motion against "
                      "each rig's data", "when": utc_now(), "code": code_version(), "machine": describe_device("cpu"),
              "load_average": load_average(),
              "setup": {"steps": args.steps, "synth_minutes": args.synth_minutes, "speech_s": args.speech_s,
                        "seeds": args.seeds, "preset": "realtime", "batch": 8, "window_s": 5, "pcs": PCS,
                        "second": args.second, "speech": SPEECH.name, "train_s": round(train_s, 1),
                        "speaker_guidance": list(args.speaker_guidance),
                        "training_skeleton": "ZEGGS (first clip)",
                        "speakers": list(bundle.config.speakers)},
              **measure(bundle, data, speakers, audio, args.seeds, tuple(args.speaker_guidance))}
    result["strips"] = render_strips(run, data, speakers, wav, folder, out.with_name(out.stem + "_frames.png"))
    write_json(out, result)
    plot(result, out.with_suffix(".png"))
    print(f"work folder: {folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
