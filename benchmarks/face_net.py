"""A probe for issue 49 ("a face listener of our own"): how far a small network trained here on phone-timed
speech gets on real voices, beside today's listener (pocketsphinx), before building it into the engine.

Data: espeak-ng passages (`dimgestor.evaluation.phone_timed`) of every language with the `--train-variants`
voices, each also once through a cheap random channel (level -20..+6 dB; a room: an exponentially decaying noise
impulse response of 50-400 ms; a spectral tilt; white or low-frequency noise at 5-35 dB SNR); with `--real-train
NAME ...`, real phone-aligned takes too (repeated `--real-repeat` times). Labels every 10 ms from the phone times:
one of nine mouth classes (silence, the vowel shapes A I U E O, lips closed M/B/P, lower lip F/V, other
consonants) and the phone's jaw opening (`dimgestor.face.visemes.OPENNESS`).

Network: 40 log-mel bands every 10 ms, each clip's mean band level removed (offline: a probe, not yet a stream),
a 5-wide convolution and five residual 3-wide dilated convolutions (1, 2, 4, 8, 1: 19 frames of context each
side), 96 channels; out: the class logits and the opening. Trained with cross-entropy + 4 x squared error.
The face: the jaw from the opening, the vowel shapes from the class probabilities, at 20 fps.

Scored with `dimgestor.face.evaluate.mouth_scores` on every real phone-aligned clip in `--data` (those not
trained on are held out) and on the held-out espeak voices (`--held-variants`), beside the shipped face
(`FaceStream`, lookahead 0.3 s) on the same real clips.

    .venv/bin/python benchmarks/face_net.py                                  # espeak-ng only
    .venv/bin/python benchmarks/face_net.py --real-train 2_scott_0_2_2 --out results/face_net_real.json
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, code_version, describe_device, load_average, utc_now, write_json

REPO = Path(__file__).resolve().parents[1]
SR, HOP, WIN, NFFT, N_MELS = 16000, 160, 400, 512, 40
CLASSES = ("SIL", "A", "I", "U", "E", "O", "MBP", "FV", "CONS")
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
    p.add_argument("--close-lips", action="store_true",
                   help="the jaw's opening times 1 - P(lips closed at M, B, P) (default: the opening alone)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=RESULTS / "face_net.json")
    p.add_argument("--note", default="measured on a shared machine: other processes were running")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def mouth_class(phone: str) -> int:
    from dimgestor.face.visemes import VOWEL_CLASS, canonical_phone

    p = canonical_phone(phone)
    if p == "SIL":
        return 0
    if p in VOWEL_CLASS:
        return 1 + "AIUEO".index(VOWEL_CLASS[p])
    return 6 if p in ("M", "B", "P") else 7 if p in ("F", "V") else 8


def log_mel(audio: np.ndarray):
    """(T, N_MELS) log mel power every 10 ms, frame t centred on t * 10 ms."""
    import torch
    import torch.nn.functional as F

    from dimgestor.frontend.mel import mel_filterbank

    x = F.pad(torch.from_numpy(np.asarray(audio, np.float32)), (WIN // 2, WIN // 2))
    spec = torch.fft.rfft(x.unfold(0, WIN, HOP) * torch.hann_window(WIN), NFFT).abs() ** 2
    return torch.log(spec @ mel_filterbank(N_MELS, NFFT, SR, 50.0, 7600.0) + 1e-8)


def targets(phones, frames: int):
    import torch

    from dimgestor.face.textgrid import phones_at
    from dimgestor.face.visemes import OPENNESS, canonical_phone

    ref = phones_at(phones, np.arange(frames) * HOP / SR)
    return (torch.tensor([mouth_class(p) for p in ref]),
            torch.tensor([OPENNESS[canonical_phone(p)] for p in ref], dtype=torch.float32))


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


def make_net(channels: int):
    import torch.nn as nn
    import torch.nn.functional as F

    class Listener(nn.Module):
        def __init__(self):
            super().__init__()
            self.inp = nn.Conv1d(N_MELS, channels, 5, padding=2)
            self.blocks = nn.ModuleList([nn.Conv1d(channels, channels, 3, padding=d, dilation=d) for d in (1, 2, 4, 8, 1)])
            self.norms = nn.ModuleList([nn.GroupNorm(1, channels) for _ in self.blocks])
            self.out = nn.Conv1d(channels, len(CLASSES) + 1, 1)

        def forward(self, x):  # (B, N_MELS, T)
            h = F.gelu(self.inp(x - x.mean(-1, keepdim=True)))
            for conv, norm in zip(self.blocks, self.norms):
                h = h + F.gelu(conv(norm(h)))
            return self.out(h)

    return Listener()


def face_of(net, audio: np.ndarray, close_lips: bool = False) -> np.ndarray:
    """(T, len(FACE_LABELS)) at 20 fps: the jaw from the opening (times 1 - P(M, B, P) with `close_lips`), the
    five vowel shapes from the probabilities."""
    import torch

    from dimgestor.face.visemes import FACE_LABELS, V

    with torch.no_grad():
        out = net(log_mel(audio).T[None])[0].T
    prob, opening = out[:, :len(CLASSES)].softmax(-1).numpy(), out[:, -1].clamp(0, 1).numpy()
    if close_lips:
        opening = opening * (1 - prob[:, CLASSES.index("MBP")])
    idx = np.minimum(np.arange(int(math.ceil(len(audio) / SR * 20))) * 5, len(opening) - 1)
    face = np.zeros((len(idx), len(FACE_LABELS)))
    face[:, V["jawOpen"]] = opening[idx]
    for k, shape in enumerate(("aa", "I", "U", "E", "O")):
        face[:, V[shape]] = prob[idx, 1 + k]
    return face


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


def main(argv=None) -> int:
    import torch
    import torch.nn.functional as F

    from dimgestor.evaluation.phone_timed import alignment, passage
    from dimgestor.face import FaceOptions
    from dimgestor.face.evaluate import mouth_scores
    from face import rounded, stream_face

    args = parse_args(argv)
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    real = real_clips(args.data)
    unknown = set(args.real_train) - set(real) | set(args.clips or ()) - set(real)
    if unknown:
        raise SystemExit(f"--real-train, --clips: no clip named {', '.join(sorted(unknown))} in {args.data}")
    load_before, t0 = load_average(), time.perf_counter()
    clips = [(f"{lang}+{v}", *(lambda s: (s.audio, alignment(s)))(passage(lang, v, seed=100 + k, sentences=args.sentences)))
             for lang in args.languages for k, v in enumerate(args.train_variants)]
    clips += [(name, *real[name]) for name in args.real_train for _ in range(args.real_repeat)]
    from dimgestor.audio import load_wav

    taught = []
    for wav in args.teacher:
        audio = load_wav(wav, SR)
        labelled = teacher_phones(audio)
        taught.append({"file": wav.name, "seconds": round(len(audio) / SR, 2), "phones": len(labelled)})
        print(f"teacher: {wav.name}, {len(audio) / SR:.0f} s, {len(labelled)} phones", flush=True)
        clips += [(wav.stem, audio, labelled)] * args.real_repeat
    data = []
    for name, audio, phones in clips:
        for heard in (audio, channel(audio, rng)):
            feats = log_mel(heard)
            data.append((feats, *targets(phones, len(feats))))
    data_s = time.perf_counter() - t0
    minutes = sum(len(d[0]) for d in data) * HOP / SR / 60
    print(f"data: {len(clips)} clips, {minutes:.1f} min with the channel copies ({data_s:.0f} s)", flush=True)

    net = make_net(args.channels)
    params = sum(p.numel() for p in net.parameters())
    opt = torch.optim.AdamW(net.parameters(), 2e-3, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(opt, 2e-3, total_steps=args.steps)
    crop = int(args.crop_s * SR / HOP)
    t1, losses = time.perf_counter(), []
    for step in range(args.steps):
        xs, cs, os_ = [], [], []
        for _ in range(args.batch):
            feats, cls, opening = data[int(rng.integers(len(data)))]
            s = int(rng.integers(0, max(1, len(feats) - crop)))
            xs.append(feats[s:s + crop]), cs.append(cls[s:s + crop]), os_.append(opening[s:s + crop])
        T = min(len(x) for x in xs)
        x = torch.stack([v[:T] for v in xs]).transpose(1, 2)
        out = net(x)
        loss = (F.cross_entropy(out[:, :len(CLASSES)], torch.stack([v[:T] for v in cs]))
                + 4 * F.mse_loss(out[:, -1], torch.stack([v[:T] for v in os_])))
        opt.zero_grad()
        loss.backward()
        opt.step()
        schedule.step()
        losses.append(float(loss.detach()))
        if step % 250 == 0 or step == args.steps - 1:
            print(f"step {step}: loss {np.mean(losses[-50:]):.3f}", flush=True)
    train_s = time.perf_counter() - t1
    net.eval()

    clips_out = {}
    for name, (audio, phones) in real.items():
        if args.clips and name not in args.clips:
            continue
        shipped, _ = stream_face(audio, 20, 0.3, FaceOptions(), SR // 10)
        clips_out[name] = {"held_out": name not in args.real_train, "seconds": round(len(audio) / SR, 2),
                           "net": rounded(mouth_scores(face_of(net, audio, args.close_lips), phones, 20)),
                           "shipped": rounded(mouth_scores(shipped, phones, 20))}
        r = clips_out[name]
        print(f"{name:26s} {'held out' if r['held_out'] else 'trained on'}: net " +
              " ".join(f"{k} {r['net'][k]:.2f}" for k in SCORES) + " | shipped " +
              " ".join(f"{k} {r['shipped'][k]:.2f}" for k in SCORES), flush=True)
    held = []
    for lang in args.languages:
        for k, v in enumerate(args.held_variants):
            s = passage(lang, v, seed=k, sentences=args.sentences)
            held.append({"voice": s.voice, **rounded(mouth_scores(face_of(net, s.audio, args.close_lips), alignment(s), 20))})
    held_mean = {k: round(float(np.nanmean([h[k] for h in held])), 4) for k in SCORES}
    print("held-out espeak-ng voices: " + " ".join(f"{k} {v:.2f}" for k, v in held_mean.items()))
    result = {"benchmark": "face_net", "code_version": code_version(), "device": describe_device("cpu"),
              "utc": utc_now(), "argv": args.argv, "note": args.note, "load_average_before": load_before,
              "params": params, "data_minutes": round(minutes, 2), "data_s": round(data_s, 1),
              "teacher": taught, "train_s": round(train_s, 1), "final_loss": round(float(np.mean(losses[-50:])), 4),
              "real": clips_out, "espeak_held_out": {"mean": held_mean, "voices": held}}
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
