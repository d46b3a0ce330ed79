"""The speech front end: streams exactly, and hears the same speech at any gain, colour or pause length."""
import numpy as np
import pytest
import torch
from scipy.signal import butter, lfilter

from dimgestor.audio import SAMPLE_RATE
from dimgestor.config import get_preset
from dimgestor.frontend.base import build_frontend
from dimgestor.frontend.speech import SPEECH_CHANNELS, SpeechFrontEnd
from dimgestor.training.synthetic import speech_and_gestures

RATE, HOP = SAMPLE_RATE, 160
LOUD, FLUX, VOICING, PITCH, PAUSE = (get_preset("realtime").n_mels + i for i in range(len(SPEECH_CHANNELS)))


@pytest.fixture(scope="module")
def fe():
    return build_frontend(get_preset("realtime", frontend="speech"))


@pytest.fixture(scope="module")
def speech():
    audio, _, events = speech_and_gestures(20.0, seed=3)
    return audio.astype(np.float32), events


def _run(fe, audio: np.ndarray, sizes=None) -> torch.Tensor:
    x = torch.from_numpy(np.ascontiguousarray(audio, dtype=np.float32))[None]
    if sizes is None:
        return fe(x, fe.init_state(1))[0][0]
    state, out, i = fe.init_state(1), [], 0
    for n in sizes:
        f, state = fe(x[:, i:i + n], state)
        out.append(f)
        i += n
    assert i == x.shape[1]
    return torch.cat(out, dim=1)[0]


def _dbfs(audio: np.ndarray, target: float) -> np.ndarray:
    """Scaled so that its loudest 1 s has RMS `target` dBFS."""
    a = audio.astype(np.float64)
    rms = max(np.sqrt(np.mean(a[i:i + RATE] ** 2)) for i in range(0, len(a) - RATE, RATE // 2))
    return (a * 10 ** (target / 20) / rms).astype(np.float32)


def _first_speech(feats: torch.Tensor) -> int:
    return int(torch.nonzero(feats[:, LOUD] > LOUD_FLOOR).flatten()[0])


LOUD_FLOOR = -45 / 20 + 1e-6


def test_shape_and_registered_by_name(fe):
    assert isinstance(fe, SpeechFrontEnd)
    f = _run(fe, np.zeros(RATE, np.float32))
    assert f.shape == (RATE // HOP, get_preset("realtime").n_mels + 5) and fe.dim == f.shape[1]
    assert fe.samples_needed(7) == 7 * HOP


@pytest.mark.parametrize("seed", [0, 1])
def test_streamed_equals_whole_for_awkward_chunks(fe, speech, seed):
    audio = speech[0][: 8 * RATE + 77]
    whole = _run(fe, audio)
    rng = np.random.default_rng(seed)
    sizes = []
    while sum(sizes) < len(audio):
        sizes.append(int(rng.choice([1, 7, 159, 160, 161, 999, 1600, 4321])))
    sizes[-1] -= sum(sizes) - len(audio)
    parts = _run(fe, audio, sizes)
    assert parts.shape == whole.shape
    assert torch.allclose(parts, whole, atol=1e-5), (parts - whole).abs().max()


def test_causal(fe, speech):
    audio = speech[0][: 4 * RATE]
    f = _run(fe, audio)
    changed = audio.copy()
    changed[2 * RATE:] = 0.3 * np.sin(np.arange(2 * RATE) * 0.05)
    g = _run(fe, changed)
    n = 2 * RATE // HOP - 2  # frames that end before the change
    assert torch.equal(f[:n], g[:n]) and not torch.equal(f[n + 3:], g[n + 3:])


def test_same_speech_at_minus_35_and_minus_10_dbfs_agrees(fe, speech):
    """The issue's gain test: after 1 s of speech the features agree within 0.05 (mean) / 0.3 (99th pct)."""
    quiet, loud = _run(fe, _dbfs(speech[0], -35.0)), _run(fe, _dbfs(speech[0], -10.0))
    start = max(_first_speech(quiet), _first_speech(loud)) + 100
    d = (quiet[start:] - loud[start:]).abs()
    assert d.mean() < 0.05 and torch.quantile(d.flatten(), 0.99) < 0.3, (d.mean(), d.max())
    # and the log-mel front end does not: the same gain moves every band by 25 dB
    lm = build_frontend(get_preset("realtime"))
    q, lo = _run(lm, _dbfs(speech[0], -35.0)), _run(lm, _dbfs(speech[0], -10.0))
    assert (q[start:] - lo[start:]).abs().mean() > 10 * d.mean()


def test_microphone_colour_is_removed(fe, speech):
    """A telephone-like band-pass (300-3400 Hz) leaves the level-free bands in its passband nearly unchanged."""
    b, a = butter(2, [300, 3400], btype="band", fs=RATE)
    phone = lfilter(b, a, speech[0]).astype(np.float32)
    f, g = _run(fe, speech[0]), _run(fe, phone)
    start = _first_speech(f) + 200
    lm_f, lm_g = (_run(build_frontend(get_preset("realtime")), x) for x in (speech[0], phone))
    pass_bands = slice(15, 45)  # mel bands well inside 300-3400 Hz
    ours = (f[start:, pass_bands] - g[start:, pass_bands]).abs().mean()
    theirs = (lm_f[start:, pass_bands] - lm_g[start:, pass_bands]).abs().mean() * 4  # log-mel: 4 units per decade
    assert ours < 0.15 and ours < theirs / 2, (ours, theirs)
    assert (f[start:, LOUD] - g[start:, LOUD]).abs().mean() < 0.15


def test_silence_reads_as_silence_at_any_gain_and_after_a_long_pause(fe, speech):
    audio = speech[0]
    gap = np.zeros(6 * RATE, np.float32)
    for target in (-40.0, -10.0):
        a = _dbfs(audio, target)
        f = _run(fe, np.concatenate([a[: 8 * RATE], gap, a[8 * RATE:]]))
        pause = f[8 * RATE // HOP + 30: 14 * RATE // HOP]
        assert torch.all(pause[:, LOUD] <= LOUD_FLOOR) and torch.all(pause[:, VOICING] == 0)
        assert torch.all(pause[:, PITCH] == 0) and torch.all(pause[:, FLUX] == 0)
        # the pause channel: 1 after 2 s of silence, back to 0 with speech
        assert torch.all(pause[-100:, PAUSE] == 1.0) and torch.all(pause[:, PAUSE].diff() >= 0)
        assert f[14 * RATE // HOP:][: 4 * RATE // HOP, PAUSE].min() == 0.0
        # the level holds through the pause: speech after it reads as before, not as a new (louder) stream
        before = _run(fe, a)[8 * RATE // HOP:][: 4 * RATE // HOP]
        after = f[14 * RATE // HOP:][: 4 * RATE // HOP]
        assert (before[:, LOUD] - after[:, LOUD]).abs().mean() < 0.05


def test_prosody_channels_follow_the_speech(fe, speech):
    audio, events = speech
    f = _run(fe, audio)
    t = (np.arange(len(f)) + 1) * HOP / RATE
    inside = np.zeros(len(f), bool)
    for a, b in events["phrases"]:
        inside |= (t > a + 0.05) & (t < b - 0.05)
    far = np.ones(len(f), bool)
    for a, b in events["phrases"]:
        far &= (t < a - 0.3) | (t > b + 0.5)
    loud, voicing = f[:, LOUD].numpy(), f[:, VOICING].numpy()
    assert loud[inside].mean() > loud[far].mean() + 1.0  # > 20 dB louder in speech than in pauses
    assert voicing[inside].mean() > 0.3 and voicing[far].max() == 0.0
    # stressed syllables are sung 15 % higher: the pitch channel sees it
    stressed = np.zeros(len(f), bool)
    for s, _ in events["stresses"]:
        stressed |= (t > s + 0.03) & (t < s + 0.1)
    pitch = f[:, PITCH].numpy()
    voiced = f[:, VOICING].numpy() > 0.45
    assert pitch[stressed & voiced].mean() > pitch[~stressed & voiced & inside].mean() + 0.05
    # onsets: the flux peaks at syllable starts
    flux = f[:, FLUX].numpy()
    onset = np.zeros(len(f), bool)
    for s, _ in events["stresses"]:
        onset |= np.abs(t - s) < 0.03
    assert flux[onset].mean() > 3 * flux[inside & ~onset].mean()


def test_batch_rows_are_independent(fe, speech):
    a = speech[0][: 3 * RATE]
    b = _dbfs(speech[0][3 * RATE: 6 * RATE], -30.0)
    both, _ = fe(torch.from_numpy(np.stack([a, b])), fe.init_state(2))
    assert torch.allclose(both[0], _run(fe, a), atol=1e-6) and torch.allclose(both[1], _run(fe, b), atol=1e-6)



def test_one_streams_statistics_are_the_batched_loops_bit_for_bit(fe, speech, monkeypatch):
    """`running_stats` of one stream (on Python floats) gives exactly the numbers of the batched loop (on arrays),
    through silence, speech, a pause and louder speech, chunk after chunk (the state carried)."""
    from dimgestor.frontend import speech as sp

    audio = np.concatenate([np.zeros(RATE // 2, np.float32), _dbfs(speech[0][: 4 * RATE], -30.0),
                            np.zeros(RATE, np.float32), speech[0][4 * RATE: 6 * RATE]])

    def run():
        state, out = fe.init_state(1), []
        for i in range(0, len(audio), 4000):
            f, state = fe(torch.from_numpy(audio[None, i:i + 4000]), state)
            out.append((f, state))
        return out

    one = run()
    stats = sp.running_stats

    def batched(energy, bands, periodicity, logf0, carried, *rest):  # two copies of the stream: the arrays' loop
        two = lambda x: np.concatenate([x, x])  # noqa: E731
        carried, *per_frame = stats(two(energy), two(bands), two(periodicity), two(logf0), tuple(map(two, carried)),
                                    *rest)
        return tuple(x[:1] for x in carried), *(x[:1] for x in per_frame)

    monkeypatch.setattr(sp, "running_stats", batched)
    for (fa, sa), (fb, sb) in zip(one, run(), strict=True):
        assert torch.equal(fa, fb)
        for x, y in zip(sa[2:], sb[2:], strict=True):  # (the floor is NaN until the first frame: none here)
            assert x.dtype == y.dtype and torch.equal(x, y)
