"""How far each listener's features move between speakers, and between microphones (issue "real voices").

A model trained on one speaker reads whatever its front end hands it; features that move when the speaker changes
(and not what was said) are what it cannot carry over to a stranger. For each listener, on the speech frames
(the frames the speech front end counts as speech) of the training speaker (the ZEGGS clip's training stretch)
and of each real unseen speaker (BEAT lawrence, two takes; BEAT2 scott, two takes; two real-world speakers):

  shift     mean over channels of |mean_A - mean_B| / pooled sd: how far the feature distribution moves
            between the training speaker and the stranger (0 = the same place)
  probe     accuracy of a linear probe (ridge LDA, trained on the first half of each recording, tested on the
            second) telling the training speaker from the stranger frame by frame: 0.5 = it cannot, 1 = always
  gain      NMSE (feature change / feature variance) of the training speech at -35 dBFS against -10 dBFS
  phone     NMSE of the training speech through a 300-3400 Hz telephone band against the full band

Listeners: `logmel` (the first default's front end), `speech` (the default's: 64 level-free bands + loudness,
flux, voicing, pitch, pause), its two parts (`speech_bands`, `speech_prosody`), the same front end with 8 and
2 bands (`speech_mel8`, `speech_mel2`: coarser spectra, less timbre), and with openwakeword installed the
`embedding` front end (speech + Google's speech embedding) and the embedding alone (`embedding_only`). Models
trained with each, scored on the same real voices: `benchmarks/listeners.py` (benchmarks/README.md, "Real voices:
what was tried").

    python benchmarks/speaker_shift.py            # ~1 min; needs ../shared (the voices)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, code_version, describe_device, real_voice, utc_now, write_json  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from dimgestor.audio import SAMPLE_RATE, load_wav  # noqa: E402
from dimgestor.config import get_preset  # noqa: E402
from dimgestor.frontend.base import build_frontend  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
ZEGGS_WAV = SHARED / "zeggs_sample" / "067_Speech_2_x_1_0.wav"
HELD_OUT_S = 15.0  # the default model's held-out tail: not part of the training speaker's features here
STRANGERS = (SHARED / "unseen_speech", SHARED / "phone_aligned_speech")  # (each file a speaker: `real_voice`)
SCHEMA = 1


def listeners() -> dict:
    """{name: (front end, channel indices or None for all)} at the default model's sizes."""
    base = get_preset("realtime").model_copy(update={"frontend": "speech", "lookahead_ms": 300, "down_kernel": 41})
    speech = build_frontend(base)
    m = base.n_mels
    return {"logmel": (build_frontend(base.model_copy(update={"frontend": "logmel"})), None),
            "speech": (speech, None),
            "speech_bands": (speech, list(range(m))),
            "speech_prosody": (speech, list(range(m, m + 5))),
            "speech_mel8": (build_frontend(base.model_copy(update={"n_mels": 8})), None),
            "speech_mel2": (build_frontend(base.model_copy(update={"n_mels": 2})), None),
            **embedding_listeners(base)}


def embedding_listeners(base) -> dict:
    """The embedding front end and its pretrained part alone, where openwakeword is installed."""
    from dimgestor.frontend.embed import model_files
    try:
        model_files()
    except (ImportError, OSError, ValueError) as e:
        print(f"skipped the embedding: {e}")
        return {}
    fe = build_frontend(base.model_copy(update={"frontend": "embedding"}))
    return {"embedding": (fe, None), "embedding_only": (fe, list(range(fe.speech.dim, fe.dim)))}


def features(fe, audio: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        f, _ = fe(torch.from_numpy(np.ascontiguousarray(audio, np.float32))[None], fe.init_state(1))
    return f[0].double().numpy()


def speech_frames(audio: np.ndarray, speech_fe) -> np.ndarray:
    """Mask of the frames the speech front end counts as speech (its pause channel still 0)."""
    f = features(speech_fe, audio)
    return f[:, -1] <= 0.0


def shift(a: np.ndarray, b: np.ndarray) -> float:
    sd = np.sqrt((a.var(0) + b.var(0)) / 2)
    keep = sd > 1e-9
    return float(np.mean(np.abs(a.mean(0) - b.mean(0))[keep] / sd[keep]))


def probe(a: np.ndarray, b: np.ndarray, ridge: float = 1e-2) -> float:
    """Ridge-LDA accuracy: trained on the first half of each, tested on the second half (balanced)."""
    ha, hb = len(a) // 2, len(b) // 2
    tr_a, te_a, tr_b, te_b = a[:ha], a[ha:], b[:hb], b[hb:]
    mu_a, mu_b = tr_a.mean(0), tr_b.mean(0)
    cov = (np.cov(tr_a, rowvar=False) + np.cov(tr_b, rowvar=False)) / 2
    cov = np.atleast_2d(cov)
    w = np.linalg.solve(cov + ridge * np.trace(cov) / len(cov) * np.eye(len(cov)), mu_a - mu_b)
    c = w @ (mu_a + mu_b) / 2
    return float(((te_a @ w > c).mean() + (te_b @ w <= c).mean()) / 2)


def nmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(((a - b) ** 2).mean() / max(b.var(0).mean(), 1e-12))


def telephone(x: np.ndarray) -> np.ndarray:
    from dimgestor.training.augment import band_limit
    return band_limit(x, 300.0, 3400.0, SAMPLE_RATE)


def at_level(x: np.ndarray, dbfs: float) -> np.ndarray:
    """x scaled so that its active speech level (`augment.active_level`, a mean power) is `dbfs`."""
    from dimgestor.training.augment import active_level
    level_db = 10 * np.log10(max(active_level(x, SAMPLE_RATE), 1e-20))
    return (x * 10 ** ((dbfs - level_db) / 20)).astype(np.float32)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(RESULTS / "speaker_shift.json"))
    args = p.parse_args()
    torch.set_num_threads(1)
    if not ZEGGS_WAV.is_file():
        print(f"skipped: {ZEGGS_WAV} not found (the voices live beside the dev checkout, in ../shared)")
        return 0
    zeggs = load_wav(ZEGGS_WAV)
    zeggs = zeggs[: len(zeggs) - int(HELD_OUT_S * SAMPLE_RATE)]
    others = {real_voice(w)[1]: load_wav(w) for folder in STRANGERS for w in sorted(folder.glob("*.wav"))}
    ls = listeners()
    speech_fe = ls["speech"][0]
    masks = {"zeggs": speech_frames(zeggs, speech_fe), **{n: speech_frames(a, speech_fe) for n, a in others.items()}}
    loud, quiet = at_level(zeggs, -10.0), at_level(zeggs, -35.0)
    rows = {}
    for name, (fe, cols) in ls.items():
        pick = (lambda f: f) if cols is None else (lambda f, c=cols: f[:, c])
        fz = pick(features(fe, zeggs))[masks["zeggs"]]
        row = {"channels": int(fz.shape[1]), "voices": {}}
        for n, a in others.items():
            fo = pick(features(fe, a))[masks[n]]
            row["voices"][n] = {"shift": shift(fz, fo), "probe": probe(fz, fo)}
        row["shift"] = float(np.mean([v["shift"] for v in row["voices"].values()]))
        row["probe"] = float(np.mean([v["probe"] for v in row["voices"].values()]))
        ref = pick(features(fe, loud))
        row["gain"] = nmse(pick(features(fe, quiet)), ref)
        row["phone"] = nmse(pick(features(fe, telephone(loud))), ref)
        rows[name] = row
        print(f"{name:16s} {row['channels']:3d} ch  shift {row['shift']:.3f}  probe {row['probe']:.3f}  "
              f"gain {row['gain']:.3f}  phone {row['phone']:.3f}")
    write_json(Path(args.out), {"benchmark": "speaker_shift", "schema": SCHEMA, "created": utc_now(),
                                "code_version": code_version(), "device": describe_device("cpu"),
                                "training_speaker": f"{ZEGGS_WAV.name}, all but the last {HELD_OUT_S:g} s",
                                "strangers": {n: f"{len(a) / SAMPLE_RATE:.1f} s" for n, a in others.items()},
                                "listeners": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
