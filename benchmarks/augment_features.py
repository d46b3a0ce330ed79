"""How much each audio augmentation changes the front-end features of real speech, and that it keeps timing.

For every effect alone (its default range, several seeds) and for the default chain, the clip is augmented
and run through the log-mel front end. Reported per effect, mean [min, max] over seeds:
- nmse: mean squared feature change / the clean clip's feature variance (mean over channels of the variance
  over time). 0 is no change; two unrelated stretches of the same speaker's speech give about 2.
- nmse_centered: the same after removing each channel's mean over the clip (what remains when a level or a
  fixed colouring is factored out: the change of the dynamics the model reads timing from).
- onset_lag_ms: the lag (within +-100 ms, 5 ms steps) at which the rises of the loudness (dB per 10 ms frame,
  5 ms hop, positive differences) of clean and augmented audio correlate best: 0 means onsets stayed put.
- loudness_lag_ms: the same for the loudness itself; a reverberant tail drags its centre of mass later
  although no onset moved.
- level_dbfs: active speech level of the result (the clean clip's beside it).

    python benchmarks/augment_features.py                  # the ZEGGS sample beside the checkout
    python benchmarks/augment_features.py --wav x.wav --seeds 4 --wav-dir /tmp/aug_wavs
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from common import RESULTS, code_version, describe_device, utc_now, write_json

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dimgestor.audio import SAMPLE_RATE, load_wav, save_wav  # noqa: E402
from dimgestor.config import get_preset  # noqa: E402
from dimgestor.frontend.base import build_frontend  # noqa: E402
from dimgestor.training.augment import AugmentConfig, active_level, augment  # noqa: E402

OFF = dict(p_pitch=0, p_formant=0, p_reverb=0, p_noise=0, p_eq=0, p_band=0, p_gain=0)
EFFECTS: dict[str, dict] = {
    "pitch (+-4 st)": dict(p_pitch=1),
    "pitch +4 st": dict(p_pitch=1, semitones=(4.0, 4.0)),
    "pitch -4 st": dict(p_pitch=1, semitones=(-4.0, -4.0)),
    "formant (0.85-1.18)": dict(p_formant=1),
    "reverb (RT60 0.2-1 s)": dict(p_reverb=1),
    "reverb RT60 1 s, wet 0.5": dict(p_reverb=1, rt60_s=(1.0, 1.0), wet=(0.5, 0.5)),
    "noise white (5-30 dB)": dict(p_noise=1, noise_kinds=("white",)),
    "noise pink (5-30 dB)": dict(p_noise=1, noise_kinds=("pink",)),
    "noise brown (5-30 dB)": dict(p_noise=1, noise_kinds=("brown",)),
    "noise babble (5-30 dB)": dict(p_noise=1, noise_kinds=("babble",)),
    "noise white 5 dB": dict(p_noise=1, noise_kinds=("white",), snr_db=(5.0, 5.0)),
    "eq (1-3 bands, +-12 dB)": dict(p_eq=1),
    "band: telephone / lowpass / highpass": dict(p_band=1),
    "gain (-30..+6 dB)": dict(p_gain=1),
    "gain -30 dB": dict(p_gain=1, gain_db=(-30.0, -30.0)),
    "default chain": None,
}


def features(fe, audio: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        f, _ = fe(torch.from_numpy(np.ascontiguousarray(audio, dtype=np.float32))[None], fe.init_state(1))
    return f[0].numpy().astype(np.float64)


HOP_MS = 5


def loudness_db(x: np.ndarray, frame: int = 160, hop: int = SAMPLE_RATE * HOP_MS // 1000) -> np.ndarray:
    n = (len(x) - frame) // hop
    idx = np.arange(frame)[None] + hop * np.arange(n)[:, None]
    return 10 * np.log10(np.mean(np.square(x.astype(np.float64)[idx]), 1) + 1e-10)


def onsets(loud: np.ndarray) -> np.ndarray:
    return np.maximum(np.diff(loud, prepend=loud[0]), 0)


def best_lag_ms(a: np.ndarray, b: np.ndarray, max_ms: int = 100) -> float:
    a, b, m = a - a.mean(), b - b.mean(), max_ms // HOP_MS
    score = [np.dot(a[max(0, -k): len(a) - max(0, k)], b[max(0, k): len(b) - max(0, -k)]) for k in range(-m, m + 1)]
    return float((int(np.argmax(score)) - m) * HOP_MS)


def summary(values: list[float], digits: int = 3) -> dict:
    return {"mean": round(float(np.mean(values)), digits), "min": round(float(np.min(values)), digits),
            "max": round(float(np.max(values)), digits)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--wav", default=None, help="speech to augment (default: the ZEGGS sample beside the checkout)")
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--wav-dir", default=None, help="also write one augmented WAV per effect here (to listen)")
    p.add_argument("--out", default=str(RESULTS / "augment_features.json"))
    args = p.parse_args()
    wav = Path(args.wav) if args.wav else next((REPO.parent / "shared" / "data" / "zeggs_sample").glob("*.wav"))
    x = load_wav(wav, SAMPLE_RATE)
    fe = build_frontend(get_preset("realtime"))
    clean = features(fe, x)
    var = float(clean.var(0).mean())
    centred = clean - clean.mean(0)
    loud = loudness_db(x)
    other = features(fe, np.roll(x, len(x) // 2))  # the same speaker saying something else at each moment
    rows = {}
    t0 = time.time()
    for name, over in EFFECTS.items():
        config = AugmentConfig() if over is None else AugmentConfig(**{**OFF, **over})
        nmse, nmse_c, lag, loud_lag, level = [], [], [], [], []
        for s in range(args.seeds):
            y = augment(x, SAMPLE_RATE, (1234, s), config, babble=[x])
            f = features(fe, y)
            nmse.append(float(np.mean((f - clean) ** 2) / var))
            nmse_c.append(float(np.mean((f - f.mean(0) - centred) ** 2) / var))
            ly = loudness_db(y)
            lag.append(best_lag_ms(onsets(loud), onsets(ly)))
            loud_lag.append(best_lag_ms(loud, ly))
            level.append(10 * np.log10(active_level(y, SAMPLE_RATE) + 1e-20))
            if args.wav_dir and s == 0:
                Path(args.wav_dir).mkdir(parents=True, exist_ok=True)
                save_wav(Path(args.wav_dir) / (name.split(" (")[0].replace(" ", "_").replace(":", "").replace("/", "")
                                               .replace(",", "") + ".wav"), y, SAMPLE_RATE)
        rows[name] = {"nmse": summary(nmse), "nmse_centered": summary(nmse_c), "onset_lag_ms": summary(lag, 1),
                      "loudness_lag_ms": summary(loud_lag, 1),
                      "level_dbfs": summary(level, 1)}
        print(f"{name:38s} nmse {np.mean(nmse):6.3f} [{min(nmse):.3f}, {max(nmse):.3f}]  centred "
              f"{np.mean(nmse_c):6.3f}  onset lag {min(lag):+.0f}..{max(lag):+.0f} ms (loudness "
              f"{min(loud_lag):+.0f}..{max(loud_lag):+.0f})  level {np.mean(level):6.1f} dBFS")
    result = {
        "what": "log-mel feature change under each audio augmentation (dimgestor.training.augment), NMSE relative to the "
                "clean clip's feature variance; loudness-envelope lag; active level",
        "audio": wav.name, "seconds": round(len(x) / SAMPLE_RATE, 1), "seeds": args.seeds,
        "clean_level_dbfs": round(10 * np.log10(active_level(x, SAMPLE_RATE)), 1),
        "reference_other_speech_nmse": round(float(np.mean((other - clean) ** 2) / var), 3),
        "reference_other_speech_nmse_centered": round(float(np.mean((other - other.mean(0) - centred) ** 2) / var), 3),
        "effects": rows, "elapsed_s": round(time.time() - t0, 1),
        "device": describe_device("cpu"), "code": code_version(), "date": utc_now(),
    }
    print(f"reference: the clip against itself shifted by half its length: nmse "
          f"{result['reference_other_speech_nmse']}, centred {result['reference_other_speech_nmse_centered']}")
    write_json(Path(args.out), result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
