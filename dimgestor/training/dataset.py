"""Folders of NAME.bvh + NAME.wav pairs -> cached features and audio -> overlapping training windows.

Clips on another skeleton than the training one (the first clip's, or the one a run names) are retargeted onto it
by their bones' names (`dimgestor.retarget`, rest poses respected), so ZEGGS' BVH, BEAT's BVH and BEAT2 / SMPL-X
takes train one model. Each clip has a speaker (`speaker_of`), for balanced sampling and the speaker condition.

Each pair is preprocessed once (BVH -> features at spec.fps, WAV -> 16 kHz mono, trimmed to the
shorter) into a cache entry keyed by the files' paths, sizes and mtimes and by the feature spec, so
a second run memory-maps the arrays instead of parsing again. Motion frame i is aligned with audio
samples [i * S, (i + 1) * S), S = SAMPLE_RATE / fps (800 at 20 fps).

Validation data: a split file (split.json / split.csv / split.txt in the folder, or `split_file`)
naming whole clips as train or valid; without one, the last `valid_fraction` of every clip (or its
last `valid_seconds`) is held out, e.g. the final ~10 s of a 69 s ZEGGS take.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from dimgestor.audio import SAMPLE_RATE, align, load_wav
from dimgestor.bvh import Skeleton, read_bvh
from dimgestor.features import (HEADING_COLUMN, VELOCITY_COLUMNS, FeatureSpec, arm_columns, mirror_features,
                                mix_arms, motion_to_features)

CACHE_VERSION = 1
SPLIT_FILES = ("split.json", "split.csv", "split.txt", "train_test_split.csv")  # (the last: BEAT2's own)


class DatasetError(ValueError):
    """A data folder that cannot be used; the message names the folder or file."""


@dataclass(frozen=True)
class Pair:
    name: str  # path relative to the data folder, without extension, "/"-separated
    bvh: Path  # its motion file: a BVH, or a BEAT2 / SMPL-X take (.npz)
    wav: Path


MOTION_SUFFIXES = (".bvh", ".npz")  # BVH, and BEAT2 / SMPL-X takes (`dimgestor.smplx`)


def read_motion(path: Path):
    """A clip's motion file as a BvhMotion: a BVH, or a BEAT2 / SMPL-X take on the generic SMPL-X skeleton."""
    if path.suffix.lower() == ".npz":
        from dimgestor.smplx import read_smplx

        return read_smplx(path)[0]
    return read_bvh(path)


_BEAT_NAME = re.compile(r"^\d+_([A-Za-z]+)_\d+_\d+_\d+$")  # BEAT / BEAT2: ID_SPEAKER_TAKE_START_END


def speaker_of(name: str, folder: str = "") -> str:
    """A clip's speaker: BEAT's naming (`2_scott_0_1_1`) gives its speaker's name; otherwise the first sub-folder
    of its name (`alice/take3` -> `alice`); otherwise `folder`, the name of the data folder it is in."""
    base = name.rsplit("/", 1)[-1]
    m = _BEAT_NAME.match(base)
    if m:
        return m.group(1).lower()
    return name.split("/", 1)[0] if "/" in name else folder


def retarget_onto(motion, skeleton: Skeleton, path: Path, onto_path: str):
    """`motion` (read from `path`) carried onto `skeleton` (the training skeleton, from `onto_path`) by its bones'
    names, each bone's rotation from its rest pose; a DatasetError naming both files when the rigs cannot be
    matched."""
    from dimgestor.retarget.rig import Rig, RigError
    from dimgestor.retarget.transfer import Retarget, resolve_map

    try:
        source, target = Rig.from_skeleton(motion.skeleton, str(path)), Rig.from_skeleton(skeleton, onto_path)
        return Retarget(source, target, resolve_map(source, what="source"), resolve_map(target)).motion(motion)
    except (RigError, ValueError) as e:
        raise DatasetError(f"{path}: its skeleton (joints, hierarchy or channels) differs from {onto_path}'s and "
                           f"cannot be retargeted onto it: {e}") from None


def find_pairs(data_dir: str | Path) -> list[Pair]:
    """All NAME.bvh (or a BEAT2 take, NAME.npz) with a NAME.wav beside it, in sub-folders too, sorted by name; a
    take in BEAT2's `smplxflame_30/` pairs with its `wave16k/NAME.wav`, as the dataset ships them."""
    root = Path(data_dir)
    if not root.is_dir():
        raise DatasetError(f"{root}: data folder not found")
    files = [p for p in root.rglob("*") if p.is_file() and not any(part.startswith(".") for part in p.relative_to(root).parts)]
    bvhs = {}
    for p in sorted(f for f in files if f.suffix.lower() in MOTION_SUFFIXES):
        if p.with_suffix("") in bvhs:
            raise DatasetError(f"{p}: {bvhs[p.with_suffix('')].name} is beside it: one motion file a clip")
        bvhs[p.with_suffix("")] = p
    wavs = {p.with_suffix(""): p for p in files if p.suffix.lower() == ".wav"}
    for stem, motion in bvhs.items():  # BEAT2's own layout: smplxflame_30/NAME.npz with wave16k/NAME.wav beside
        if stem not in wavs and motion.parent.name.startswith("smplxflame"):
            beside = motion.parent.parent / "wave16k" / motion.stem
            if beside in wavs:
                wavs[stem] = wavs.pop(beside)
    pairs = [Pair(stem.relative_to(root).as_posix(), bvhs[stem], wavs[stem]) for stem in sorted(bvhs.keys() & wavs.keys())]
    if not pairs:
        raise DatasetError(
            f"{root}: no NAME.bvh (or NAME.npz) + NAME.wav pairs found ({len(bvhs)} motion and {len(wavs)} .wav files; "
            "a pair is a BVH or BEAT2 take and a WAV with the same name in the same folder)"
        )
    lonely = sorted(str(p.relative_to(root)) for stem, p in {**bvhs, **wavs}.items() if stem not in bvhs or stem not in wavs)
    if lonely:
        warnings.warn(f"{root}: {len(lonely)} files without a partner are ignored: {', '.join(lonely[:5])}"
                      + (" ..." if len(lonely) > 5 else ""), stacklevel=2)
    return pairs


def read_split(path: str | Path, names: list[str]) -> dict[str, str]:
    """A split file -> {pair name: "train" | "valid"}; clips it does not name are train.

    JSON: {"train": [...], "valid": [...]}. CSV / TXT: one clip per line, `NAME,valid` or
    `NAME valid` (a `name,split` header and # comments are skipped). Names may omit sub-folders.
    BEAT2's `train_test_split.csv` (`id,type`: train, val, test or additional) reads the same way, test and val
    held out, additional trained on, takes it names that are not in the folder skipped.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise DatasetError(f"{path}: cannot read split file: {e.strerror or e}") from None
    entries: list[tuple[str, str, int]] = []
    if path.suffix.lower() == ".json":
        try:
            d = json.loads(text)
            entries = [(str(n), s, 0) for s in ("train", "valid") for n in d.get(s, [])]
        except (json.JSONDecodeError, AttributeError, TypeError) as e:
            raise DatasetError(f"{path}: not a split JSON of the form {{\"train\": [...], \"valid\": [...]}}: {e}") from None
    else:
        for lineno, line in enumerate(text.splitlines(), 1):
            row = next(csv.reader([line.split("#")[0]]), []) if "," in line else line.split("#")[0].split()
            row = [c.strip() for c in row if c.strip()]
            if not row or [c.lower() for c in row] in (["name", "split"], ["id", "type"]):
                continue
            if len(row) != 2:
                raise DatasetError(f"{path}:{lineno}: expected 'NAME,train' or 'NAME valid', got {line!r}")
            entries.append((row[0], row[1].lower(), lineno))
    split: dict[str, str] = {}
    for name, which, lineno in entries:
        which = {"validation": "valid", "val": "valid", "test": "valid", "additional": "train"}.get(which, which)
        if which not in ("train", "valid"):
            raise DatasetError(f"{path}:{lineno}: split must be train or valid, got {which!r}")
        match = [n for n in names if n == name or n.rsplit("/", 1)[-1] == name]
        if not match and path.name == "train_test_split.csv":
            continue  # BEAT2's list names every take of its language: one may train on some of them
        if not match:
            raise DatasetError(f"{path}:{lineno}: {name!r} is not one of the pairs in the data folder")
        for n in match:
            split[n] = which
    return {n: split.get(n, "train") for n in names}


def default_cache_dir() -> Path:
    base = os.environ.get("DIMGESTOR_CACHE") or os.path.join(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"), "dimgestor")
    return Path(base) / "datasets"


@dataclass
class Clip:
    name: str
    features: np.ndarray  # (T, D) float32, raw (not normalized)
    audio: np.ndarray  # (T * samples_per_frame,) float32, 16 kHz
    skeleton: Skeleton
    retargeted: bool = False  # its motion file is on another skeleton, carried onto this one


def speed_perturb(clip: Clip, rate: float, fps: float, spf: int, heading: str = "velocity") -> Clip:
    """The clip played `rate` times faster, audio and motion together (pitch moves with the tempo, as in
    Ko et al.'s speed perturbation for speech): rotations, height and a "facing" heading are interpolated in
    time, per-frame root displacements (and a "velocity" heading's turns) scaled by `rate`."""
    from fractions import Fraction

    from scipy.signal import resample_poly

    f = np.asarray(clip.features, dtype=np.float64)
    T = int(len(f) / rate)
    src = np.arange(T) * rate  # source frame of each new frame
    i0 = np.minimum(src.astype(int), len(f) - 1)
    i1 = np.minimum(i0 + 1, len(f) - 1)
    w = (src - i0)[:, None]
    out = (1 - w) * f[i0] + w * f[i1]
    out[:, list(VELOCITY_COLUMNS) + ([HEADING_COLUMN] if heading == "velocity" else [])] *= rate
    q = Fraction(rate).limit_denominator(100)
    audio = resample_poly(np.asarray(clip.audio, dtype=np.float64), q.denominator, q.numerator)
    audio = np.pad(audio, (0, max(0, T * spf - len(audio))))[: T * spf]
    return Clip(f"{clip.name}@{rate:g}x", out.astype(np.float32), audio.astype(np.float32), clip.skeleton)


def _cache_key(pair: Pair, spec: FeatureSpec, onto: Skeleton | None = None) -> str:
    stats = {str(p.resolve()): [p.stat().st_size, p.stat().st_mtime_ns] for p in (pair.bvh, pair.wav)}
    key = {"v": CACHE_VERSION, "files": stats, "spec": spec.to_dict(), "rate": SAMPLE_RATE}
    if onto is not None:
        key["onto"] = onto.to_dict()
    blob = json.dumps(key, sort_keys=True, default=lambda a: np.asarray(a).tolist())
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def preprocess_pair(pair: Pair, spec: FeatureSpec, onto: Skeleton | None = None, onto_path: str = "") -> Clip:
    """Read, featurize and align one pair (no cache); its motion retargeted onto `onto` (from `onto_path`) when
    its skeleton is another."""
    motion = read_motion(pair.bvh)
    retargeted = onto is not None and not motion.skeleton.same_topology(onto)
    if retargeted:
        motion = retarget_onto(motion, onto, pair.bvh, onto_path or "the training skeleton")
    features = motion_to_features(motion, spec)
    audio = load_wav(pair.wav, SAMPLE_RATE)
    spf = samples_per_frame(spec)
    _, audio = align(len(features) / spec.fps, audio, SAMPLE_RATE, name=pair.name)
    T = min(len(features), len(audio) // spf)
    return Clip(pair.name, features[:T], audio[: T * spf], motion.skeleton, retargeted)


def load_clip(pair: Pair, spec: FeatureSpec, cache_dir: Path | None, onto: Skeleton | None = None,
              onto_path: str = "") -> Clip:
    """preprocess_pair through the cache: arrays are memory-mapped when the entry exists."""
    if cache_dir is None:
        return preprocess_pair(pair, spec, onto, onto_path)
    entry = cache_dir / f"{pair.name.replace('/', '__')}-{_cache_key(pair, spec, onto)}"
    if (entry / "meta.json").is_file():
        try:
            meta = json.loads((entry / "meta.json").read_text())
            return Clip(pair.name, np.load(entry / "features.npy", mmap_mode="r"), np.load(entry / "audio.npy", mmap_mode="r"),
                        Skeleton.from_dict(meta["skeleton"]), bool(meta.get("retargeted", False)))
        except (OSError, ValueError, KeyError):
            shutil.rmtree(entry, ignore_errors=True)  # a damaged entry is rebuilt below
    clip = preprocess_pair(pair, spec, onto, onto_path)
    tmp = entry.with_name(entry.name + f".tmp{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    np.save(tmp / "features.npy", clip.features)
    np.save(tmp / "audio.npy", clip.audio)
    (tmp / "meta.json").write_text(json.dumps({"skeleton": clip.skeleton.to_dict(), "bvh": str(pair.bvh), "wav": str(pair.wav),
                                               "retargeted": clip.retargeted}))
    try:
        os.replace(tmp, entry)
    except OSError:  # another process wrote the same entry first: theirs is as good
        shutil.rmtree(tmp, ignore_errors=True)
    return clip


def samples_per_frame(spec: FeatureSpec) -> int:
    spf = SAMPLE_RATE / spec.fps
    if abs(spf - round(spf)) > 1e-9:
        raise ValueError(f"fps {spec.fps} does not divide {SAMPLE_RATE} Hz into whole samples per frame")
    return int(round(spf))


class GestureDataset:
    """Windows of `window_s` seconds (hop `hop_s`, default half a window) over one split of one or more folders.

    Items: {"motion": (W, D) float32 raw features, "audio": (W * 800,) float32, "name", "start_frame",
    "mirrored", "arms", "speaker"} (+ "audio_features" when audio_feature_fn is given). A stretch shorter than one
    window yields one shorter item; `collate_windows` crops a batch to its shortest item.
    cache_dir defaults to $DIMGESTOR_CACHE or ~/.cache/dimgestor/datasets; use_cache=False skips it.
    Several folders: their clips are named FOLDER/NAME (the folder's own name), each folder's split file
    applies to its clips. `skeleton`: the training skeleton (a Skeleton, or a BVH / BEAT2 take whose skeleton it
    is); default the first clip's. Clips on another skeleton are retargeted onto it (`retargeted` names them).
    """

    def __init__(self, data_dir: str | Path | Sequence[str | Path], spec: FeatureSpec | None = None,
                 window_s: float = 20.0, hop_s: float | None = None, split: str = "train",
                 cache_dir: str | Path | None = None, use_cache: bool = True, mirror: bool = False,
                 audio_feature_fn: Callable[[np.ndarray], np.ndarray] | None = None,
                 valid_fraction: float = 0.15, valid_seconds: float | None = None, split_file: str | Path | None = None,
                 speeds: tuple[float, ...] = (), arm_mix: bool = False, skeleton: Skeleton | str | Path | None = None):
        if split not in ("train", "valid"):
            raise ValueError(f"split must be 'train' or 'valid', got {split!r}")
        folders = [Path(d) for d in ([data_dir] if isinstance(data_dir, (str, os.PathLike)) else data_dir)]
        if not folders:
            raise DatasetError("no data folder given")
        self.data_dirs = folders
        self.data_dir = folders[0]
        labels = _folder_labels(folders)
        self.pairs: list[Pair] = []
        self.speaker_by_clip: dict[str, str] = {}  # clip name -> speaker
        by_clip: dict[str, str] = {}
        for folder, label in zip(folders, labels):
            pairs = find_pairs(folder)
            names = [p.name for p in pairs]
            own = split_file if split_file is not None else next(
                (folder / f for f in SPLIT_FILES if (folder / f).is_file()), None)
            which = read_split(own, names) if own else {}
            for p in pairs:
                name = f"{label}/{p.name}" if len(folders) > 1 else p.name
                self.pairs.append(Pair(name, p.bvh, p.wav))
                self.speaker_by_clip[name] = speaker_of(p.name, label)
                if own:
                    by_clip[name] = which[p.name]
        spec = spec or FeatureSpec()
        cache = (Path(cache_dir) if cache_dir is not None else default_cache_dir()) if use_cache else None
        onto, onto_path = self._training_skeleton(skeleton)
        first = load_clip(self.pairs[0], spec, cache, onto, onto_path)
        onto = onto or first.skeleton
        onto_path = onto_path or str(self.pairs[0].bvh)
        self.clips = [first] + [load_clip(p, spec, cache, onto, onto_path) for p in self.pairs[1:]]
        self.retargeted = [p.name for p, c in zip(self.pairs, self.clips) if c.retargeted]
        self.skeleton = self._common_skeleton(onto, onto_path)
        self.spec = spec.resolve(self.skeleton)
        self.fps = self.spec.fps
        self.spf = samples_per_frame(self.spec)
        self.split, self.mirror, self.audio_feature_fn = split, mirror, audio_feature_fn
        self.clip_speakers = [self.speaker_by_clip[p.name] for p in self.pairs]  # per clip (speed copies appended below)
        # segments: (clip index, first frame, end frame) of this split
        self.segments: list[tuple[int, int, int]] = []
        for c, (pair, clip) in enumerate(zip(self.pairs, self.clips)):
            T = len(clip.features)
            if pair.name in by_clip:
                if by_clip[pair.name] == split:
                    self.segments.append((c, 0, T))
                continue
            n_valid = int(round(valid_seconds * self.fps)) if valid_seconds is not None else int(round(valid_fraction * T))
            cut = max(0, T - n_valid)
            seg = (c, 0, cut) if split == "train" else (c, cut, T)
            if seg[2] > seg[1]:
                self.segments.append(seg)
        if split == "train":  # speed-perturbed copies of the training part only: nothing held out leaks in
            for c, a, b in list(self.segments):
                for rate in speeds:
                    if rate <= 0:
                        raise ValueError(f"speed factors must be positive, got {rate}")
                    if rate == 1.0:
                        continue
                    part = Clip(self.clips[c].name, self.clips[c].features[a:b],
                                self.clips[c].audio[a * self.spf:b * self.spf], self.clips[c].skeleton)
                    self.clips.append(speed_perturb(part, rate, self.fps, self.spf, self.spec.heading))
                    self.clip_speakers.append(self.clip_speakers[c])
                    self.segments.append((len(self.clips) - 1, 0, len(self.clips[-1].features)))
        self.window = max(1, int(round(window_s * self.fps)))
        self.hop = max(1, int(round((hop_s if hop_s is not None else window_s / 2) * self.fps)))
        # (clip, first frame, frames, variant): variant False = as captured, True = mirrored, "left"/"right" =
        # that arm on both sides (mix_arms; training only, one per window, the sides taking turns)
        starts = [(c, s, e - s) for c, a, b in self.segments for s, e in self._starts(a, b)]
        self.arm_mix = bool(arm_mix) and split == "train"
        if self.arm_mix and not len(arm_columns(self.spec, self.skeleton)[0]):
            raise DatasetError(f"{self.data_dir}: arm mixing needs left and right arm joints among the features "
                               f"(joints named Left*/Right*, L_*/R_* or *.l/*.r below the spine); none were found")
        self.windows = [(c, s, n, m) for k, (c, s, n) in enumerate(starts)
                        for m in ((False, True) if mirror else (False,))
                        + ((("left", "right")[k % 2],) if self.arm_mix else ())]
        if not self.windows:
            raise DatasetError(f"{self.data_dir}: the {split!r} split is empty "
                               f"({len(self.clips)} clips; check the split file or valid_fraction)")

    @property
    def speakers(self) -> list[str]:
        """Every speaker of the data (both splits), sorted."""
        return sorted(set(self.speaker_by_clip.values()))

    def window_speakers(self) -> list[str]:
        """The speaker of each window, in window order."""
        return [self.clip_speakers[c] for c, _, _, _ in self.windows]

    def _training_skeleton(self, skeleton) -> tuple[Skeleton | None, str]:
        if skeleton is None or isinstance(skeleton, Skeleton):
            return skeleton, ("the given skeleton" if skeleton is not None else "")
        path = Path(skeleton)
        if path.suffix.lower() not in MOTION_SUFFIXES:
            raise DatasetError(f"{path}: the training skeleton is read from a BVH or a BEAT2 / SMPL-X take (.npz)")
        if not path.is_file():
            raise DatasetError(f"{path}: training skeleton file not found")
        return read_motion(path).skeleton, str(path)

    def _common_skeleton(self, onto: Skeleton, onto_path: str) -> Skeleton:
        """The training skeleton; one warning for all the clips whose bones are of other lengths."""
        other = [str(p.bvh) for p, c in zip(self.pairs, self.clips) if not c.retargeted
                 and not np.allclose(c.skeleton.offsets, onto.offsets, atol=1e-3)]
        if other:
            warnings.warn(f"{other[0]}" + (f" and {len(other) - 1} more clips" if len(other) > 1 else "")
                          + f": bone offsets differ from {onto_path}; features are rotations, so training works, "
                          "but generated motion uses the training skeleton's bones", stacklevel=3)
        return onto

    def _starts(self, a: int, b: int) -> list[tuple[int, int]]:
        if b - a <= self.window:
            return [(a, b)]
        starts = list(range(a, b - self.window + 1, self.hop))
        if starts[-1] != b - self.window:  # cover the tail too
            starts.append(b - self.window)
        return [(s, s + self.window) for s in starts]

    @property
    def motion_dim(self) -> int:
        return self.spec.dim

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, i: int) -> dict:
        c, start, n, variant = self.windows[i]
        clip = self.clips[c]
        motion = np.array(clip.features[start:start + n], dtype=np.float32)
        if variant is True:
            motion = mirror_features(motion, self.spec).astype(np.float32)
        elif variant:
            motion = mix_arms(motion, self.spec, self.skeleton, variant).astype(np.float32)
        audio = np.array(clip.audio[start * self.spf:(start + n) * self.spf], dtype=np.float32)
        item = {"motion": motion, "audio": audio, "name": clip.name, "start_frame": start,
                "mirrored": variant is True, "arms": variant if isinstance(variant, str) else None,
                "speaker": self.clip_speakers[c]}
        if self.audio_feature_fn is not None:
            item["audio_features"] = self.audio_feature_fn(audio)
        return item

    def frames(self) -> np.ndarray:
        """Every frame of this split once (mirrored copies too when mirroring), (N, D) float32."""
        parts = [np.asarray(self.clips[c].features[a:b]) for c, a, b in self.segments]
        if self.mirror:
            parts += [mirror_features(p, self.spec) for p in parts]
        return np.concatenate(parts).astype(np.float32)

    def seconds(self) -> float:
        """Length of this split (speed-perturbed copies included) in seconds."""
        return sum(b - a for _, a, b in self.segments) / self.fps

    def summary(self) -> str:
        seconds = self.seconds()
        speakers = sorted(set(self.window_speakers()))
        moved = len(self.retargeted)
        return (f"{self.split}: {len(self.clips)} clips, {seconds:.1f} s, {len(self)} windows of "
                f"{self.window / self.fps:g} s, {self.motion_dim} features at {self.fps:g} fps"
                + (", mirrored" if self.mirror else "")
                + (", arm-mixed" if self.arm_mix else "")
                + (", with speed-perturbed copies" if len(self.clips) > len(self.pairs) else "")
                + (f", {moved} clip{'s' * (moved != 1)} retargeted onto the training skeleton" if moved else "")
                + (f", {len(speakers)} speakers" if len(speakers) > 1 else ""))


def _folder_labels(folders: list[Path]) -> list[str]:
    """Each data folder's name, made unique (`a`, `a-2`) when two folders share one."""
    labels, seen = [], {}
    for f in folders:
        base = f.resolve().name or "data"
        seen[base] = seen.get(base, 0) + 1
        labels.append(base if seen[base] == 1 else f"{base}-{seen[base]}")
    return labels


def compute_stats(dataset: GestureDataset, min_std: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Per-column mean and std over the split's frames; std floored so constant columns stay finite."""
    frames = dataset.frames().astype(np.float64)
    return frames.mean(0).astype(np.float32), np.maximum(frames.std(0), min_std).astype(np.float32)


def collate_windows(items: list[dict]) -> dict:
    """Stack items into a batch, cropping every window to the shortest one (frames and samples alike)."""
    n = min(len(it["motion"]) for it in items)
    spf = len(items[0]["audio"]) // max(len(items[0]["motion"]), 1)
    batch = {"motion": np.stack([it["motion"][:n] for it in items]),
             "audio": np.stack([it["audio"][: n * spf] for it in items]),
             "name": [it["name"] for it in items], "start_frame": [it["start_frame"] for it in items]}
    if "audio_features" in items[0]:
        batch["audio_features"] = [it["audio_features"] for it in items]
    return batch
