"""Trains the face's own listener (`dimgestor/face/net.py`, issue 49) and scores it on real voices beside the
pocketsphinx listener; `--save` writes the weights the package ships (`dimgestor/face/listener.safetensors`).

Data: espeak-ng passages (`dimgestor.evaluation.phone_timed`) of every language with the `--train-variants`
voices, each also once through a random channel (level -20..+6 dB; a room: an exponentially decaying noise
impulse response of 50-400 ms; a spectral tilt; white or low-frequency noise at 5-35 dB SNR; with `--formants`,
the formants moved by a random ratio, the project's voice augmentation); with `--real-train NAME ...`, real
phone-aligned takes too, and with `--teacher WAV ...` real speech without an alignment labelled by pocketsphinx's
phone recognizer over the whole recording (each repeated `--real-repeat` times, also through the channel).
Labels every 10 ms from the phone times: the phone's viseme (one of 15) and the jaw's opening
(`dimgestor.face.visemes`).

The network and its features are the engine's (`dimgestor.face.net`: causal log-mels against a running mean,
0.13 s of lookahead); trained with cross-entropy + 4 x squared error on `--crop-s` crops.

Scored with `dimgestor.face.evaluate.mouth_scores` on every real phone-aligned clip in `--data` (those not
trained on are held out; the face the engine makes, `FaceStream` with this listener, streamed in 100 ms pieces)
and on the held-out espeak voices (`--held-variants`), beside the pocketsphinx face on the same real clips.

    .venv/bin/python benchmarks/face_net.py                                  # espeak-ng only
    .venv/bin/python benchmarks/face_net.py --real-train 2_scott_0_2_2 --teacher WAV... --save dimgestor/face/listener.safetensors
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json

REPO = Path(__file__).resolve().parents[1]
SR = 16000
SCORES = ("openness_r", "vowel_top1", "vowel_mean_recall", "closures", "rest")


def parse_args(argv=None) -> argparse.Namespace:
    from dimgestor.evaluation.phone_timed import LANGUAGES

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "phone_aligned_speech",
                   help="folder of the real phone-aligned clips (WAV + TextGrid)")
    p.add_argument("--languages", nargs="+", default=list(LANGUAGES), choices=LANGUAGES, metavar="LANG")
    p.add_argument("--train-variants", nargs="+",
                   default=["m1", "m2", "m4", "m5", "m6", "f1", "f3", "f4", "klatt", "klatt2", "klatt4"])
    p.add_argument("--held-variants", nargs="+", default=["m3", "f2", "klatt3"])
    p.add_argument("--sentences", type=int, default=None, help="sentences per passage (default: all)")
    p.add_argument("--clips", nargs="+", default=None, metavar="NAME", help="real clips to score (default: all)")
    p.add_argument("--real-train", nargs="*", default=[], metavar="NAME", help="real clips to train on too")
    p.add_argument("--real-repeat", type=int, default=8, help="copies of each real training clip in the data")
    p.add_argument("--teacher", nargs="*", type=Path, default=[], metavar="WAV",
                   help="real speech without an alignment, labelled by pocketsphinx's phone recognizer (the shipped "
                        "listener's) over the whole recording, trained on --real-repeat times")
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--crop-s", type=float, default=4.0, help="training crops")
    p.add_argument("--channels", type=int, default=96)
    p.add_argument("--formants", action="store_true", help="the channel copies' formants moved too (0.85-1.2)")
    p.add_argument("--band", type=float, default=0.0,
                   help="the share of channel copies also band-limited (high-pass 80-400 Hz, low-pass 3-7 kHz: "
                        "telephones, headsets, laptop microphones)")
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--balance", type=float, default=0.0,
                   help="weigh each viseme class by its frequency to this power, negated (0.5: rare shapes count "
                        "more; 0: every frame alike)")
    p.add_argument("--save", type=Path, default=None, help="write the weights here (safetensors)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=RESULTS / "face_net.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def channel(audio: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """`audio` through a random level, room, tilt and noise (see the module's docstring)."""
    a = np.asarray(audio, np.float64) * 10 ** (rng.uniform(-20, 6) / 20)
    if rng.random() < 0.7:
        n = int(SR * rng.uniform(0.05, 0.4))
        ir = rng.standard_normal(n) * np.exp(-np.arange(n) / (SR * rng.uniform(0.02, 0.12)))
        ir[0] = 1 / rng.uniform(0.3, 1.0)
        ir /= np.sqrt(np.sum(ir ** 2))
        a = np.fft.irfft(np.fft.rfft(a, len(a) + n) * np.fft.rfft(ir, len(a) + n))[:len(a)]
    if rng.random() < 0.7:
        k = rng.uniform(-0.9, 0.9)
        a = np.concatenate([a[:1], a[1:] - k * a[:-1]])
    if rng.random() < 0.8:
        noise = rng.standard_normal(len(a))
        if rng.random() < 0.5:  # low-frequency rumble
            noise = np.cumsum(noise)
            noise -= np.convolve(noise, np.ones(200) / 200, "same")
        level = np.mean(a ** 2) / 10 ** (rng.uniform(5, 35) / 10)
        a = a + noise * np.sqrt(level / max(np.mean(noise ** 2), 1e-20))
    return a.astype(np.float32)


def teacher_phones(audio: np.ndarray, pause_s: float = 0.3) -> list[tuple[float, float, str]]:
    """Phones of real speech as pocketsphinx's phone recognizer hears the whole recording (the shipped listener's
    acoustic model and phone language model, decoded offline: every phone with all the context after it), one
    utterance per stretch between pauses of `pause_s` (40 ms RMS 35 dB under the recording's loud frames)."""
    from dimgestor.face.listener import phone_decoder

    decoder = phone_decoder()
    hop = SR // 100
    frames = len(audio) // hop
    db = 10 * np.log10(np.mean(audio[:frames * hop].reshape(frames, hop) ** 2, axis=1) + 1e-12)
    loud = np.convolve(db > np.percentile(db, 95) - 35, np.ones(4), "same") > 0
    quiet_run, cuts, start = 0, [], 0
    for i, on in enumerate(loud):  # utterances: cut in the middle of each pause of pause_s or more
        quiet_run = 0 if on else quiet_run + 1
        if quiet_run == int(pause_s * 100):
            cuts.append((start, i - quiet_run // 2))
            start = i - quiet_run // 2
    cuts.append((start, frames))
    pcm = (np.clip(audio, -1, 1) * 32767).astype(np.int16)
    out = []
    for a, b in cuts:
        decoder.start_utt()
        decoder.process_raw(pcm[a * hop:b * hop].tobytes(), False, True)
        decoder.end_utt()
        out += [(a / 100 + seg.start_frame / 100, a / 100 + (seg.end_frame + 1) / 100, seg.word)
                for seg in decoder.seg() or ()]
    return out


def real_clips(folder: Path) -> dict:
    from dimgestor.audio import load_wav
    from dimgestor.face.textgrid import read_tiers

    if not folder.is_dir():
        raise SystemExit(f"{folder}: the phone-aligned clips are not there (--data)")
    return {w.stem: (load_wav(w, SR), read_tiers(w.with_suffix(".TextGrid"))["phones"])
            for w in sorted(folder.glob("*.wav")) if w.with_suffix(".TextGrid").is_file()}


def features(audio: np.ndarray, phones=None):
    """(log-mel bands, viseme classes, openings) every 10 ms of a whole recording (frame t at t * 10 ms)."""
    import torch

    from dimgestor.face.net import CLASSES, HOP, log_mel
    from dimgestor.face.textgrid import phones_at
    from dimgestor.face.visemes import OPENNESS, canonical_phone, viseme_of

    mel = log_mel(audio)
    if phones is None:
        return mel, None, None
    ref = phones_at(phones, np.arange(len(mel)) * HOP / SR)
    return (mel, torch.tensor([CLASSES.index(viseme_of(p)) for p in ref]),
            torch.tensor([OPENNESS[canonical_phone(p)] for p in ref], dtype=torch.float32))


def heard_through(audio: np.ndarray, rng: np.random.Generator, formants: bool, band: float = 0.0) -> np.ndarray:
    """A copy through a random channel (and, with `formants`, another vocal tract's length; with `band`, that
    share band-limited)."""
    from dimgestor.training.augment import band_limit, formant_shift

    if formants and rng.random() < 0.7:
        audio = formant_shift(np.asarray(audio, np.float64), float(rng.uniform(0.85, 1.2)), SR).astype(np.float32)
    if rng.random() < band:
        audio = band_limit(np.asarray(audio, np.float64), float(rng.uniform(80, 400)), float(rng.uniform(3000, 7000)),
                           SR).astype(np.float32)
    return channel(audio, rng)


def engine_face(audio: np.ndarray, weights: Path | None, **options) -> np.ndarray:
    """The face the engine streams (100 ms pieces, lookahead 0.3 s) with the network listener (`weights`) or
    pocketsphinx (None)."""
    from dimgestor.face import FaceOptions
    from face import stream_face

    opts = FaceOptions(listener="net", weights=str(weights), **options) if weights else FaceOptions(
        listener="pocketsphinx", **options)
    return stream_face(audio, 20, 0.3, opts, SR // 10)[0]


def main(argv=None) -> int:
    import tempfile

    import torch
    import torch.nn.functional as F

    from dimgestor.audio import load_wav
    from dimgestor.evaluation.phone_timed import alignment, passage
    from dimgestor.face.evaluate import mouth_scores
    from dimgestor.face.net import CLASSES, LAYERS, normalise, save_weights, torch_listener
    from face import rounded

    args = parse_args(argv)
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    real = real_clips(args.data)
    unknown = set(args.real_train) - set(real) | set(args.clips or ()) - set(real)
    if unknown:
        raise SystemExit(f"--real-train, --clips: no clip named {', '.join(sorted(unknown))} in {args.data}")
    load_before, t0 = load_average(), time.perf_counter()
    synthetic = [(f"{lang}+{v}", *(lambda s: (s.audio, alignment(s)))(passage(lang, v, seed=100 + k,
                                                                              sentences=args.sentences)))
                 for lang in args.languages for k, v in enumerate(args.train_variants)]
    reals = [(name, *real[name]) for name in args.real_train]
    taught = []
    for wav in args.teacher:
        audio = load_wav(wav, SR)
        labelled = teacher_phones(audio)
        taught.append({"file": wav.name, "seconds": round(len(audio) / SR, 2), "phones": len(labelled)})
        print(f"teacher: {wav.name}, {len(audio) / SR:.0f} s, {len(labelled)} phones", flush=True)
        reals.append((wav.stem, audio, labelled))
    raw = []   # (mel, classes, openings, weight): each synthetic clip clean and through a channel; each real one
    for name, audio, phones in synthetic:   # clean once and through --real-repeat - 1 channels
        for heard in (audio, heard_through(audio, rng, args.formants, args.band)):
            raw.append((*features(heard, phones), 1))
    for name, audio, phones in reals:
        clean = features(audio, phones)
        raw.append((*clean, 1))
        for _ in range(args.real_repeat - 1):
            raw.append((*features(heard_through(audio, rng, args.formants, args.band), phones)[:1], *clean[1:], 1))
    prior = np.mean(np.concatenate([m for m, *_ in raw]), axis=0)
    data = [(torch.from_numpy(normalise(m, None, prior)[0]), c, o) for m, c, o, _ in raw]
    data_s = time.perf_counter() - t0
    minutes = sum(len(d[0]) for d in data) / 100 / 60
    print(f"data: {len(data)} clips with the channel copies, {minutes:.1f} min ({data_s:.0f} s)", flush=True)

    counts = torch.bincount(torch.cat([c for _, c, _ in data]), minlength=len(CLASSES)).double()
    class_weight = ((counts.clamp(min=1) / counts.sum()) ** -args.balance).float()
    class_weight /= (class_weight * counts.float()).sum() / counts.sum()  # the mean frame weight stays 1
    net = torch_listener(args.channels)
    net.prior[:] = torch.from_numpy(prior)
    params = sum(p.numel() for p in net.parameters())
    opt = torch.optim.AdamW(net.parameters(), args.lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(opt, args.lr, total_steps=args.steps)
    crop = int(args.crop_s * 100)
    t1, losses = time.perf_counter(), []
    for step in range(args.steps):
        xs, cs, os_ = [], [], []
        for _ in range(args.batch):
            feats, cls, opening = data[int(rng.integers(len(data)))]
            s = int(rng.integers(0, max(1, len(feats) - crop)))
            xs.append(feats[s:s + crop]), cs.append(cls[s:s + crop]), os_.append(opening[s:s + crop])
        T = min(len(x) for x in xs)
        out = net(torch.stack([v[:T] for v in xs]))
        loss = (F.cross_entropy(out[..., :len(CLASSES)].reshape(-1, len(CLASSES)), torch.stack([v[:T] for v in cs]).reshape(-1),
                                weight=class_weight)
                + 4 * F.mse_loss(out[..., -1], torch.stack([v[:T] for v in os_])))
        opt.zero_grad()
        loss.backward()
        opt.step()
        schedule.step()
        losses.append(float(loss.detach()))
        if step % 250 == 0 or step == args.steps - 1:
            print(f"step {step}: loss {np.mean(losses[-50:]):.3f}", flush=True)
    train_s = time.perf_counter() - t1
    net.eval()
    training = {"argv": args.argv, "code_version": code_version(), "utc": utc_now(), "steps": args.steps,
                "data_minutes": round(minutes, 2), "languages": args.languages,
                "train_variants": args.train_variants, "real_train": args.real_train,
                "teacher": [t["file"] for t in taught], "layers": [list(x) for x in LAYERS], "params": params,
                "class_frames": {c: int(n) for c, n in zip(CLASSES, counts.tolist())}, "balance": args.balance,
                "formants": args.formants, "band": args.band}
    weights = args.save or Path(tempfile.mkdtemp()) / "listener.safetensors"
    save_weights(net, weights, training)

    clips_out = {}
    for name, (audio, phones) in real.items():
        if args.clips and name not in args.clips:
            continue
        clips_out[name] = {"held_out": name not in args.real_train, "seconds": round(len(audio) / SR, 2),
                           "net": rounded(mouth_scores(engine_face(audio, weights), phones, 20)),
                           "net_unlevelled": rounded(mouth_scores(engine_face(audio, weights, loud_range_db=1e4),
                                                                  phones, 20)),
                           "pocketsphinx": rounded(mouth_scores(engine_face(audio, None), phones, 20))}
        r = clips_out[name]
        print(f"{name:26s} {'held out' if r['held_out'] else 'trained on'}: " + " | ".join(
            f"{kind} " + " ".join(f"{r[kind][k]:.2f}" for k in SCORES)
            for kind in ("net", "net_unlevelled", "pocketsphinx")), flush=True)
    held = []
    for lang in args.languages:
        for k, v in enumerate(args.held_variants):
            s = passage(lang, v, seed=k, sentences=args.sentences)
            held.append({"voice": s.voice, **rounded(mouth_scores(engine_face(s.audio, weights), alignment(s), 20))})
    held_mean = {k: round(float(np.nanmean([h[k] for h in held])), 4) for k in SCORES}
    print("held-out espeak-ng voices: " + " ".join(f"{k} {v:.2f}" for k, v in held_mean.items()))
    result = {"benchmark": "face_net", "code_version": code_version(), "device": describe_device("cpu"),
              "utc": utc_now(), "argv": args.argv, "note": args.note, "load_average_before": load_before,
              "params": params, "data_minutes": round(minutes, 2), "data_s": round(data_s, 1),
              "teacher": taught, "train_s": round(train_s, 1), "final_loss": round(float(np.mean(losses[-50:])), 4),
              "saved": str(args.save) if args.save else None,
              "real": clips_out, "espeak_held_out": {"mean": held_mean, "voices": held}}
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
