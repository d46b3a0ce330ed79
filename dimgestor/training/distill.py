"""`dimgestor distill`: a trained model -> a student of one network row a pass, in 1 or 2 passes or in the
teacher's own steps with its guidance folded in (issue "cost").

The teacher is the checkpoint as it streams: its K-step DDIM chain with classifier-free guidance (two network rows
a step). The student starts as a copy of it and learns to give, in `--steps` passes of one row (guidance folded in,
so its config's guidance is 1), what the teacher's whole chain gives from the same starting noise and the same
speech (knowledge distillation, Luhman & Luhman 2021; the teacher's chain is deterministic: DDIM with eta 0).

Both run on whole training windows as the stream runs them: the network is causal and its Mamba-2 states are
carried frame to frame, so a window's output is what a stream makes frame by frame, and the student streams
exactly as any model does (streamed = offline, any chunking, batched = alone). Its carried states are its own
passes'. Only the audio of the training data is used (the teacher labels it), with augmented copies of it (other
voices, rooms and microphones, as `train --augment` makes them): the held-out stretch of the teacher's training
stays held out. `--audio` adds speech that has no motion at all (any WAV files: other speakers, other languages):
the teacher labels it as it labels the training audio, so the student learns the teacher's answer to many voices
rather than to the training speaker's few minutes. The loss: the mean squared difference to the teacher's motion,
and of its frame-to-frame velocity and acceleration (a one-pass student otherwise smooths away the teacher's
fastest motion or adds jitter); with `--spread-weight`, also of the difference between two noises' motions for the
same speech (what sets one seed's motion apart from another's).

A student learnt by the mean squared difference moves less than its teacher: where the starting noise leaves the
teacher's answer uncertain, the mean of its answers is smaller than any of them. With `--calibrate`, each checkpoint
is calibrated: on a fixed set of the windows it learns from, each motion feature's frame-to-frame change is measured
in the teacher's motion and in the student's, and the student's sampled motion is scaled per feature by their ratio
(its mean moved to the teacher's), in its weights (`DiMGestor.calibrate`), so it moves as much as its teacher
wherever it streams (torch, ONNX Runtime, the browser). It is off by default: for the shipped default model it gave
the student the teacher's liveliness back only in part, at a worse FGD (benchmarks/README.md, *A one-pass student*).

With `--steps` equal to the teacher's own steps, the student folds the guidance in step by step instead (Meng et al.
2023, "On distillation of guided diffusion models", its first stage): at every step of the teacher's chain, on the
teacher's own noisy motion of that step, it learns in its one row the guided output of the teacher's two rows. Its
chain is the teacher's and only the unconditional row goes, so a window costs about half, and each step's answer is
one the student can give exactly rather than the mean of several (what makes shorter students move less, above).
The loss is the squared difference of the outputs; `--vel-weight`, `--acc-weight` and `--spread-weight` are for
students of fewer steps than their teacher's.

A teacher of one row a step (its guidance folded in, or none) whose step count `--steps` divides is distilled
progressively instead (Salimans & Ho 2022; Meng et al. 2023, its second stage): each of the student's steps spans r
of the teacher's, starting where the span starts on the teacher's own chain, and learns the x0 whose one DDIM step
lands exactly where the teacher's r steps land (`Diffusion.x0_reaching`). Again each answer is one the student can
give exactly, not the mean of several. The student's steps are every r-th of its teacher's (the config's
`ddim_timesteps`): a 4-step folded teacher on t = 7, 5, 2, 0 gives a 2-step student on 7, 2.
"""
from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..audio import load_wav
from ..config import exact_div
from ..model.diffusion import Diffusion, check_guidance, ddim_pairs, guide
from ..model.network import DiMGestor
from ..streaming.checkpoint import load_checkpoint, save_checkpoint
from .augment import AugmentConfig, augment
from .dataset import GestureDataset
from .train import WindowBank

__all__ = ["DistillConfig", "SpeechBank", "distill", "register", "teacher_motion", "teacher_steps", "teacher_spans",
           "teacher_chain", "student_motion", "calibration", "student_pairs"]

GAIN_RANGE = (0.5, 2.0)  # a feature's calibration gain is kept inside this (one the student barely moves stays sane)


class DistillConfig(BaseModel):
    """What `dimgestor distill` is given: validated once, saved in the student's checkpoint (info["distill"])."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    checkpoint: str | None = None  # the teacher (None: the embedded default model)
    init: str | None = None  # a student to go on from (an earlier run's checkpoint); None: the teacher's weights
    out: str  # the run folder: ckpt_XXXXXXX/ checkpoints and log.jsonl
    steps: int = Field(2, ge=1, le=64)  # the student's sampler steps (network passes a window), no more than the
    # teacher's: its own count folds its guidance in step by step; a divisor of it, from a teacher of one row a step,
    # learns progressively; otherwise the teacher's whole chain (`student_pairs`)
    guidance: float | None = Field(None, gt=0)  # the teacher's classifier-free guidance scale (None: its config's)
    data: str | None = None  # BVH+WAV folder whose audio the teacher labels (None: the teacher's own training data)
    audio: tuple[str, ...] = ()  # WAV files or folders of speech without motion, labelled by the teacher too
    audio_share: float = Field(0.5, ge=0, le=1)  # of each batch's windows, the share drawn from `audio`
    max_steps: int = Field(1000, gt=0)
    batch_size: int = Field(8, gt=0)
    lr: float = Field(1e-4, gt=0)
    warmup: int = Field(50, ge=0)
    grad_clip: float = Field(1.0, ge=0)
    ema: float = Field(0.995, ge=0, lt=1)
    vel_weight: float = Field(4.0, ge=0)  # weight of the velocity difference (frame to frame)
    acc_weight: float = Field(4.0, ge=0)  # of the acceleration difference (1 and 1 left a 1-pass student's wrists
    # 1.77x the real capture's jerk, 4 and 4 1.49x: benchmarks/README.md, "A one-pass student")
    spread_weight: float = Field(0.0, ge=0)  # of the difference between two noises' motions for one window's speech
    calibrate: bool = False  # scale the student's motion per feature to move as much as the teacher's (module doc)
    calibration_windows: int = Field(128, gt=0)  # the windows it is measured on (drawn as batches are)
    aug_copies: int = Field(4, ge=0)  # augmented versions of each window's audio (0: the clean audio alone)
    window_s: float | None = Field(None, gt=0)  # None: the teacher's
    valid_every: int = Field(200, ge=0)
    ckpt_every: int = Field(500, gt=0)
    seed: int = 0
    device: str = "cpu"
    cache_dir: str | None = None  # the dataset's feature cache (None: $DIMGESTOR_CACHE or ~/.cache/dimgestor)


def teacher_chain(model: DiMGestor, diffusion: Diffusion, pairs, cond: torch.Tensor, x: torch.Tensor,
                  guidance: float):
    """The teacher's chain on whole windows, step by step: cond (B, T, H), x_T (B, T, D); DDIM with eta 0 and
    classifier-free guidance `guidance` (the unconditional row's condition zeroed, as its streams run it). Yields
    each step's (t, the noisy motion x_t, the (guided) output there, x_t_prev), in the chain's order."""
    B = x.shape[0]
    c = torch.cat([cond, torch.zeros_like(cond)]) if guidance != 1.0 else cond
    for t, t_prev in pairs:
        out, _ = model(torch.cat([x, x]) if guidance != 1.0 else x, t, c)
        if guidance != 1.0:
            out = guide(out[:B], out[B:], guidance)
        eps, x0 = diffusion.split(out, x, t)
        x_prev = diffusion.ddim_step(x, eps, t, t_prev, 0.0, None, x0=x0)[0]
        yield t, x, out, x_prev
        x = x_prev


def teacher_motion(model: DiMGestor, diffusion: Diffusion, pairs, cond: torch.Tensor, x: torch.Tensor,
                   guidance: float) -> torch.Tensor:
    """The teacher's whole chain: x_T (B, T, D) -> x0 (B, T, D)."""
    for *_, x in teacher_chain(model, diffusion, pairs, cond, x, guidance):
        pass
    return x


def _steps_of(B: int, t: int, device) -> torch.Tensor:
    return torch.full((B,), t, dtype=torch.long, device=device)


def teacher_steps(model: DiMGestor, diffusion: Diffusion, pairs, cond: torch.Tensor, x: torch.Tensor,
                  guidance: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every step of the teacher's guided chain, for a student that folds its guidance in: (inputs (K*B, T, D):
    each step's noisy motion, steps (K*B,): its t, outputs (K*B, T, D): the guided output of the teacher's two
    rows there), in the chain's order, B rows a step."""
    steps = list(teacher_chain(model, diffusion, pairs, cond, x, guidance))
    return (torch.cat([x_t for _, x_t, _, _ in steps]), torch.cat([_steps_of(len(x), t, x.device) for t, *_ in steps]),
            torch.cat([out for _, _, out, _ in steps]))


def teacher_spans(model: DiMGestor, diffusion: Diffusion, pairs, r: int, cond: torch.Tensor, x: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The teacher's chain (one row a step, no guidance: a folded or unguided teacher) in spans of `r` steps, for a
    progressively distilled student whose step is one span: (inputs (K/r*B, T, D): the noisy motion where each
    span starts, steps (K/r*B,): its t, targets (K/r*B, T, D): the x0 whose one DDIM step lands where the teacher's
    r steps land), in the chain's order, B rows a span."""
    steps = list(teacher_chain(model, diffusion, pairs, cond, x, 1.0))
    spans = [(steps[i][0], steps[i][1], steps[i + r - 1][3], pairs[i + r - 1][1]) for i in range(0, len(steps), r)]
    return (torch.cat([start for _, start, _, _ in spans]),
            torch.cat([_steps_of(len(x), t0, x.device) for t0, *_ in spans]),
            torch.cat([diffusion.x0_reaching(start, end, t0, t_end) for t0, start, end, t_end in spans]))


def student_motion(model: DiMGestor, diffusion: Diffusion, pairs, cond: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """The student's chain (one row a pass, no guidance): as `teacher_motion` with guidance 1."""
    return teacher_motion(model, diffusion, pairs, cond, x, 1.0)


class SpeechBank:
    """Front-end features of windows of speech that has no motion (`--audio`), for the teacher to label.

    Each file is heard whole, as a stream hears it: the front end's state is carried from its first sample, and
    silence is padded after its end for the last frames' lookahead. It is cut into windows of `frames` motion
    frames every `frames // 2`. With `copies` > 0, as many augmented versions of each file (other voices, rooms,
    microphones; seeded by (seed, file, copy)) are cut the same way, and `batch` picks a window's version.
    """

    def __init__(self, paths, model: DiMGestor, frames: int, device, copies: int = 0,
                 aug_config: AugmentConfig | None = None, seed: int = 0):
        c = model.config
        self.copies, self.frames = copies, frames
        self.files = speech_files(paths)
        self.seconds = 0.0
        self.feats: list[torch.Tensor] = []  # window i: (copies + 1, features, width)
        spf = exact_div(c.sample_rate, c.fps, "samples per motion frame")
        n = frames * c.feats_per_frame + c.lookahead_feats
        with torch.no_grad():
            for k, path in enumerate(self.files):
                try:
                    audio = load_wav(path, c.sample_rate)
                except (ValueError, OSError, EOFError) as e:
                    raise ValueError(f"--audio {path}: not a readable WAV file ({e})") from e
                total = len(audio) // spf
                if total < frames:
                    continue  # shorter than one window
                self.seconds += len(audio) / c.sample_rate
                versions = [audio] + [augment(audio, c.sample_rate, (seed, 1_000_003 + k, j), aug_config)
                                      for j in range(copies)]
                heard = [self._features(model, v, total, device) for v in versions]
                for start in range(0, total - frames + 1, max(frames // 2, 1)):
                    a = start * c.feats_per_frame
                    self.feats.append(torch.stack([f[a: a + n] for f in heard]))

    @staticmethod
    def _features(model: DiMGestor, audio: np.ndarray, frames: int, device) -> torch.Tensor:
        padded = np.zeros(max(model.samples_needed(frames), len(audio)), np.float32)
        padded[: len(audio)] = audio
        fe = model.frontend
        return fe(torch.from_numpy(padded)[None].to(device), fe.init_state(1, device))[0][0].cpu()

    def __len__(self) -> int:
        return len(self.feats)

    def batch(self, idx: list[int], g: torch.Generator) -> torch.Tensor:
        """(B, features, width): each window's clean audio or one of its augmented versions, drawn uniformly."""
        pick = torch.randint(0, self.copies + 1, (len(idx),), generator=g).tolist()
        return torch.stack([self.feats[i][v] for i, v in zip(idx, pick)])


def speech_files(paths) -> list[Path]:
    """The WAV files of `paths` (files, or folders searched recursively), sorted within each folder; a path that
    does not exist, or a folder without WAV files, is refused by name."""
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(f for f in p.rglob("*") if f.suffix.lower() == ".wav" and f.is_file())
            if not found:
                raise ValueError(f"--audio {p}: no .wav files in this folder")
            files += found
        elif p.is_file():
            files.append(p)
        else:
            raise FileNotFoundError(f"--audio {p}: no such file or folder")
    return files


def student_pairs(t_pairs: list[tuple[int, int]], steps: int, guidance: float, N: int, spacing: str
                  ) -> tuple[str, list[tuple[int, int]]]:
    """How a `steps`-step student learns from a teacher sampling on `t_pairs` with `guidance`, and its own steps:
    "fold" (the teacher's steps, its guidance folded in), "progressive" (an unguided or folded teacher, `steps`
    dividing its count: each student step spans that many of the teacher's) or "chain" (the teacher's whole chain
    on the student's own `ddim_pairs`)."""
    K = len(t_pairs)
    if steps > K:
        raise ValueError(f"--steps {steps}: more than the teacher's own {K} steps")
    if steps == K:
        if guidance == 1.0:
            raise ValueError(f"--steps {steps}: the teacher already samples in {steps} passes of one row "
                             f"(guidance 1); its student needs fewer steps")
        return "fold", list(t_pairs)
    if guidance == 1.0 and K % steps == 0:
        r = K // steps
        return "progressive", [(t_pairs[i][0], t_pairs[i + r - 1][1]) for i in range(0, K, r)]
    return "chain", ddim_pairs(steps, N, spacing)


def _loss(pred: torch.Tensor, target: torch.Tensor, cfg: DistillConfig) -> torch.Tensor:
    loss = F.mse_loss(pred, target)
    for order, weight in ((1, cfg.vel_weight), (2, cfg.acc_weight)):
        if weight > 0 and pred.shape[1] > order:
            loss = loss + weight * F.mse_loss(pred.diff(n=order, dim=1), target.diff(n=order, dim=1))
    return loss


def _heard(bank: WindowBank, speech: SpeechBank | None, idx: list[int], g: torch.Generator, c
           ) -> tuple[torch.Tensor, int]:
    """The features of a batch drawn from the training windows (indices below len(bank)) and the --audio windows
    (the rest), cropped to the shortest; and its frames."""
    mine = [i for i in idx if i < len(bank)]
    theirs = [i - len(bank) for i in idx if i >= len(bank)]
    parts = []
    if mine:
        parts.append(bank.batch(mine, c.lookahead_feats, c.feats_per_frame, bank.draw_versions(len(mine), g))[1])
    if theirs:
        parts.append(speech.batch(theirs, g))
    T = (min(p.shape[1] for p in parts) - c.lookahead_feats) // c.feats_per_frame
    return torch.cat([p[:, : T * c.feats_per_frame + c.lookahead_feats] for p in parts]), T


def calibration(teacher: list[torch.Tensor], student: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """(gain, shift), each (D,): what makes the student's motion move as the teacher's on the same windows and noise
    (teacher[i], student[i]: (B, T, D) batches of windows): per feature, the ratio of the spreads of their
    frame-to-frame changes (1 where the teacher's feature does not move; within GAIN_RANGE), and the shift that then
    gives the student's motion the teacher's mean."""
    def spread(xs):  # (changes inside each window only)
        return torch.cat([x.diff(dim=1).flatten(0, 1) for x in xs]).double().std(0)

    def mean(xs):
        return torch.cat([x.flatten(0, 1) for x in xs]).double().mean(0)

    spread_t, spread_s = spread(teacher), spread(student)
    gain = torch.where(spread_t > 1e-6, spread_t / spread_s.clamp_min(1e-9), torch.ones_like(spread_t))
    gain = gain.clamp(*GAIN_RANGE)
    return gain.float(), (mean(teacher) - gain * mean(student)).float()


def _log(out: Path, record: dict) -> None:
    with open(out / "log.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


def distill(cfg: DistillConfig, progress: bool = True) -> Path:
    """Distil `cfg.checkpoint` into a `cfg.steps`-pass student; returns its last checkpoint folder."""
    from tqdm import tqdm

    out = Path(cfg.out)
    if out.exists() and any(out.glob("ckpt_*")):
        raise ValueError(f"{out} already holds checkpoints: choose a new --out")
    speech_files(cfg.audio)  # refused by name before anything loads
    torch.manual_seed(cfg.seed)
    device = torch.device(cfg.device)
    bundle = load_checkpoint(cfg.checkpoint, device)
    teacher = bundle.model.eval().requires_grad_(False)
    tc = teacher.config
    opts = bundle.info.get("options", {})
    data = cfg.data or bundle.info.get("data")
    folders = [data] if isinstance(data, str) else list(data or ())
    if not folders or not all(Path(f).is_dir() for f in folders):
        raise ValueError(f"--data: the BVH+WAV folder whose audio the teacher labels (the checkpoint names "
                         f"{bundle.info.get('data')!r}, which is not a folder here)")
    guidance = check_guidance(tc.guidance if cfg.guidance is None else cfg.guidance)
    diffusion = Diffusion(tc)
    t_pairs = diffusion.sampling_pairs("ddim", tc.sample_steps)
    method, s_pairs = student_pairs(t_pairs, cfg.steps, guidance, diffusion.N, tc.ddim_spacing)
    fold, span = method == "fold", len(t_pairs) // cfg.steps
    if method != "chain" and cfg.spread_weight > 0:
        raise ValueError(f"--spread-weight: for a student that learns its teacher's whole chain, not a {method} one")
    timesteps = None if method == "chain" else tuple(t for t, _ in s_pairs)
    student_config = tc.model_copy(update={"sample_steps": cfg.steps, "guidance": 1.0, "calibrated": cfg.calibrate,
                                           "ddim_timesteps": timesteps})
    student = DiMGestor(student_config).to(device)
    start = teacher if cfg.init is None else load_checkpoint(cfg.init, device).model
    if cfg.init is not None and (start.config.sample_steps, start.config.guidance) != (cfg.steps, 1.0):
        raise ValueError(f"--init {cfg.init}: a student of {start.config.sample_steps} step(s) with guidance "
                         f"{start.config.guidance:g}, not of --steps {cfg.steps}")
    weights = {k: v for k, v in start.state_dict().items() if k not in ("out_gain", "out_shift")}
    missing, unexpected = student.load_state_dict(weights, strict=False)  # (calibrated again below)
    if unexpected or set(missing) - {"out_gain", "out_shift"}:
        raise ValueError(f"the student's weights do not fit its start ({missing[:5]}, {unexpected[:5]})")
    ema = copy.deepcopy(student).requires_grad_(False).eval()
    split = dict(window_s=cfg.window_s or opts.get("window_s", 5.0), valid_fraction=opts.get("valid_fraction", 0.15),
                 valid_seconds=opts.get("valid_seconds"))
    split.update(hop_s=split["window_s"] / 4, cache_dir=cfg.cache_dir, skeleton=bundle.skeleton)
    train_ds = GestureDataset(folders, bundle.feature_spec, split="train", speeds=tuple(opts.get("speeds") or ()), **split)
    valid_ds = GestureDataset(folders, bundle.feature_spec, split="valid", **split)
    t0 = time.time()
    bank = WindowBank(train_ds, teacher, bundle.mean, bundle.std, device, copies=cfg.aug_copies,
                      aug_config=AugmentConfig(), seed=cfg.seed)
    valid = WindowBank(valid_ds, teacher, bundle.mean, bundle.std, device) if cfg.valid_every else None
    frames = max(len(m) for m in bank.motion)
    speech = SpeechBank(cfg.audio, teacher, frames, device, copies=cfg.aug_copies, seed=cfg.seed) if cfg.audio else None
    if speech is not None and not len(speech):
        raise ValueError(f"--audio: no file is as long as one window ({frames / tc.fps:g} s)")
    out.mkdir(parents=True, exist_ok=True)
    extra = f", {len(speech)} windows of --audio speech ({speech.seconds / 60:.1f} min)" if speech else ""
    rows = len(t_pairs) * (2 if guidance != 1 else 1)
    how = {"fold": " (the guidance folded in, step by step)", "chain": " (the teacher's whole chain)",
           "progressive": f" (each step {span} of the teacher's, progressively)"}[method]
    print(f"teacher {bundle.path}: {tc.sample_steps} steps, guidance {guidance:g} ({rows} network rows a window); "
          f"student: {cfg.steps} step(s), 1 row{how}; "
          f"{len(bank)} training windows x {cfg.aug_copies + 1} versions of their audio{extra} "
          f"({time.time() - t0:.0f} s), {len(valid or [])} held out")
    g = torch.Generator().manual_seed(cfg.seed * 1000 + 1)
    opt = torch.optim.AdamW(student.parameters(), lr=cfg.lr, weight_decay=0.0)
    c = tc

    def validation() -> float:
        gv = torch.Generator().manual_seed(cfg.seed + 7919)
        total = 0.0
        with torch.no_grad():
            for i in range(len(valid)):
                _, feats = valid.batch([i], c.lookahead_feats, c.feats_per_frame)
                feats = feats.to(device)
                cond_t = teacher.condition(feats)[0]
                T = valid.motion[i].shape[0]
                x = diffusion.noise_like(torch.zeros(1, T, c.motion_dim), gv).to(device)
                target = teacher_motion(teacher, diffusion, t_pairs, cond_t[:, :T], x, guidance)
                pred = student_motion(ema, diffusion, s_pairs, ema.condition(feats)[0][:, :T], x)
                total += _loss(pred, target, cfg).item()
        return total / max(len(valid), 1)

    gc = torch.Generator().manual_seed(cfg.seed * 1000 + 3)
    calib: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []  # (features, x_T, the teacher's motion)
    n_calib = min(cfg.calibration_windows, len(bank) * (cfg.aug_copies + 1) + (len(speech) if speech else 0))
    if cfg.calibrate:
        pool = torch.randperm(len(bank), generator=gc).tolist() * (cfg.aug_copies + 1)
        pool = pool[:n_calib - round(n_calib * cfg.audio_share)] if speech is not None else pool[:n_calib]
        if speech is not None:
            pool += (torch.randperm(len(speech), generator=gc) + len(bank)).tolist()[:n_calib - len(pool)]
        with torch.no_grad():
            for a in range(0, len(pool), cfg.batch_size):
                feats, T = _heard(bank, speech, pool[a:a + cfg.batch_size], gc, c)
                feats = feats.to(device)
                x = diffusion.noise_like(torch.zeros(len(feats), T, c.motion_dim), gc).to(device)
                calib.append((feats, x, teacher_motion(teacher, diffusion, t_pairs, teacher.condition(feats)[0][:, :T],
                                                       x, guidance)))

    def calibrated() -> dict:
        """The EMA student's calibration against the teacher on the fixed windows, set in its weights."""
        with torch.no_grad():
            mine = [student_motion(ema, diffusion, s_pairs, ema.condition(f)[0][:, :x.shape[1]], x)
                    for f, x, _ in calib]
            gain, shift = calibration([t for _, _, t in calib], mine)
        ema.out_gain.copy_(gain)
        ema.out_shift.copy_(shift)
        return {"windows": sum(len(f) for f, _, _ in calib), "gain_min": gain.min().item(),
                "gain_median": gain.median().item(), "gain_max": gain.max().item()}

    last = out
    if valid is not None:
        _log(out, {"step": 0, "valid_loss": validation()})
    bar = tqdm(total=cfg.max_steps, disable=not progress, dynamic_ncols=True, desc="distill")
    smooth, t_start = None, time.time()
    n_speech = round(cfg.batch_size * cfg.audio_share) if speech is not None else 0
    n_own = cfg.batch_size - n_speech
    order, speech_order = [], []
    for step in range(1, cfg.max_steps + 1):
        if len(order) < n_own:
            order += torch.randperm(len(bank), generator=g).tolist()
        while len(speech_order) < n_speech:
            speech_order += (torch.randperm(len(speech), generator=g) + len(bank)).tolist()
        idx, order = order[:n_own], order[n_own:]
        idx, speech_order = idx + speech_order[:n_speech], speech_order[n_speech:]
        feats, T = _heard(bank, speech, idx, g, c)
        if cfg.spread_weight > 0:  # each window twice, with two noises: the first half's windows again
            half = len(idx) // 2
            feats = torch.cat([feats[:half], feats[:half]])
        feats = feats.to(device)
        x = diffusion.noise_like(torch.zeros(len(feats), T, c.motion_dim), g).to(device)
        student.train()
        if fold:
            with torch.no_grad():
                xs, ts, target = teacher_steps(teacher, diffusion, t_pairs, teacher.condition(feats)[0][:, :T], x,
                                               guidance)
            cond = student.condition(feats)[0][:, :T]
            loss = F.mse_loss(student(xs, ts, cond.repeat(len(t_pairs), 1, 1))[0], target)
        elif method == "progressive":
            with torch.no_grad():
                xs, _, target = teacher_spans(teacher, diffusion, t_pairs, span, teacher.condition(feats)[0][:, :T], x)
            cond = student.condition(feats)[0][:, :T]
            B = len(feats)
            given = student(xs, torch.cat([torch.full((B,), t, dtype=torch.long) for t, _ in s_pairs]).to(device),
                            cond.repeat(cfg.steps, 1, 1))[0]
            pred = torch.cat([diffusion.split(given[k * B:(k + 1) * B], xs[k * B:(k + 1) * B], t)[1]
                              for k, (t, _) in enumerate(s_pairs)])
            loss = _loss(pred, target, cfg)
        else:
            with torch.no_grad():
                target = teacher_motion(teacher, diffusion, t_pairs, teacher.condition(feats)[0][:, :T], x, guidance)
            pred = student_motion(student, diffusion, s_pairs, student.condition(feats)[0][:, :T], x)
            loss = _loss(pred, target, cfg)
        if cfg.spread_weight > 0:
            loss = loss + cfg.spread_weight * F.mse_loss(pred[:half] - pred[half:], target[:half] - target[half:])
        for group in opt.param_groups:
            group["lr"] = cfg.lr * min(1.0, step / max(cfg.warmup, 1))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(student.parameters(), cfg.grad_clip)
        opt.step()
        decay = min(cfg.ema, (1 + step) / (10 + step))
        with torch.no_grad():
            for pe, pm in zip(ema.parameters(), student.parameters()):
                pe.lerp_(pm, 1 - decay)
        smooth = loss.item() if smooth is None else 0.98 * smooth + 0.02 * loss.item()
        bar.update(1)
        bar.set_postfix(loss=f"{smooth:.4f}", refresh=False)
        record = {"step": step, "train_loss": smooth, "elapsed_s": round(time.time() - t_start, 1)}
        if valid is not None and (step % cfg.valid_every == 0 or step == cfg.max_steps):
            record["valid_loss"] = validation()
            bar.set_postfix(loss=f"{smooth:.4f}", valid=f"{record['valid_loss']:.4f}")
        if "valid_loss" in record or step == cfg.max_steps:
            _log(out, record)
        if step % cfg.ckpt_every == 0 or step == cfg.max_steps:
            taught = {k: bundle.info[k] for k in ("step", "history", "train_wall_s", "teacher") if k in bundle.info}
            info = {**{k: v for k, v in bundle.info.items() if k != "train_wall_s"}, "step": step,
                    "distilled_from": str(bundle.path), "history": [record], "distill": cfg.model_dump(),
                    "teacher": {"sample_steps": tc.sample_steps, "guidance": guidance, **taught}, "method": method}
            if cfg.calibrate:
                info["calibration"] = calibrated()
            last = save_checkpoint(out / f"ckpt_{step:07d}", ema, bundle.feature_spec, bundle.skeleton, bundle.mean,
                                   bundle.std, info=info)
    bar.close()
    return last


# ---------------- CLI ----------------
def register(subparsers) -> None:
    from ..cli_help import examples

    p = subparsers.add_parser(
        "distill", help="distil a trained model into a student of one network row a pass (1 or 2 passes, "
                        "guidance folded into the teacher's steps, or a one-row teacher's steps halved)",
        description="Distil a checkpoint (its K-step sampler with guidance, two network rows a step) into a "
                    "student that gives the same motion in --steps passes of one row: several times cheaper a "
                    "window, streamed exactly as any model. Only the audio of the data is used (the teacher labels "
                    "it).",
        epilog=examples("dimgestor distill --checkpoint runs/mine/ckpt_0004000 --out runs/mine_2pass",
                        "dimgestor distill --out runs/default_1pass --steps 1 --data ../shared/data/zeggs_sample",
                        "dimgestor distill --checkpoint runs/mine --out runs/mine_folded --steps 4",
                        "dimgestor distill --checkpoint runs/mine_folded --out runs/mine_2step --steps 2",
                        "dimgestor generate --audio speech.wav --out motion.bvh --checkpoint runs/mine_2pass"))
    d = DistillConfig(out="")
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="the teacher: a checkpoint folder, a run folder (its latest), 'default' or 'live' "
                        "(default: the embedded default model)")
    p.add_argument("--out", required=True, metavar="DIR", help="run folder for the student's checkpoints and log.jsonl")
    p.add_argument("--steps", type=int, default=d.steps, metavar="K",
                   help="the student's network passes a window. The teacher's own step count folds its guidance in, "
                        "step by step (about half the cost a window); fewer steps from a teacher of one row a step "
                        "(folded, or unguided), dividing its count: each student step learns that many of the "
                        "teacher's (progressive); otherwise the student learns the teacher's whole chain")
    p.add_argument("--guidance", type=float, default=None, metavar="S",
                   help="the teacher's classifier-free guidance scale (default: its config's)")
    p.add_argument("--init", default=None, metavar="DIR",
                   help="go on from this student (an earlier run's checkpoint) instead of the teacher's weights")
    p.add_argument("--data", default=None, metavar="DIR",
                   help="BVH+WAV folder whose audio the teacher labels (default: the one the teacher was trained on)")
    p.add_argument("--audio", action="append", default=[], metavar="PATH",
                   help="speech without motion for the teacher to label as well: a WAV file or a folder of them "
                        "(searched recursively); may be given several times")
    p.add_argument("--audio-share", type=float, default=d.audio_share, metavar="F",
                   help="the share of each batch drawn from --audio, the rest from the data's own windows")
    p.add_argument("--max-steps", type=int, default=d.max_steps, metavar="N", help="optimizer steps")
    p.add_argument("--batch-size", type=int, default=d.batch_size, metavar="N", help="training windows a step")
    p.add_argument("--lr", type=float, default=d.lr, help="peak learning rate (AdamW)")
    p.add_argument("--vel-weight", type=float, default=d.vel_weight, metavar="W",
                   help="weight of the difference in frame-to-frame velocity to the teacher's motion")
    p.add_argument("--acc-weight", type=float, default=d.acc_weight, metavar="W",
                   help="weight of the difference in acceleration (the student's own jitter)")
    p.add_argument("--spread-weight", type=float, default=d.spread_weight, metavar="W",
                   help="weight of the difference between the motions of two noises for the same speech (half of "
                        "each batch repeats the other half's windows with other noise); 0: off")
    p.add_argument("--calibrate", action="store_true",
                   help="scale each checkpoint's motion per feature to move as much as the teacher's, measured on "
                        "--calibration-windows windows (livelier, further from the real capture's distribution)")
    p.add_argument("--calibration-windows", type=int, default=d.calibration_windows, metavar="N",
                   help="windows of the training audio (and --audio) the calibration is measured on")
    p.add_argument("--aug-copies", type=int, default=d.aug_copies, metavar="N",
                   help="augmented versions of each window's audio (other voices, rooms, microphones); 0: none")
    p.add_argument("--valid-every", type=int, default=d.valid_every, metavar="N",
                   help="the distillation loss on the held-out windows every N steps (log.jsonl); 0: never")
    p.add_argument("--ckpt-every", type=int, default=d.ckpt_every, metavar="N", help="save the student every N steps")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the batches, the noise and the augmentation")
    p.add_argument("--device", default=d.device, help="torch device: cpu, cuda, cuda:1, ...")
    p.add_argument("--threads", type=int, default=None, metavar="N", help="CPU threads for torch")
    p.add_argument("--cache-dir", default=None, metavar="DIR",
                   help="dataset feature cache (default: $DIMGESTOR_CACHE or ~/.cache/dimgestor)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (log.jsonl is written all the same)")
    p.set_defaults(func=_run)


def _run(args) -> int:
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        cfg = DistillConfig(checkpoint=args.checkpoint, init=args.init, out=args.out, steps=args.steps,
                            guidance=args.guidance, data=args.data,
                            audio=tuple(args.audio), audio_share=args.audio_share,
                            max_steps=args.max_steps, batch_size=args.batch_size, lr=args.lr,
                            vel_weight=args.vel_weight, acc_weight=args.acc_weight, spread_weight=args.spread_weight,
                            calibrate=args.calibrate, calibration_windows=args.calibration_windows,
                            aug_copies=args.aug_copies, valid_every=args.valid_every, ckpt_every=args.ckpt_every,
                            seed=args.seed, device=args.device, cache_dir=args.cache_dir)
    except ValidationError as e:
        raise SystemExit(f"dimgestor distill: {e.errors()[0]['loc'][0]}: {e.errors()[0]['msg']}")
    try:
        last = distill(cfg, progress=not args.no_progress)
    except (ValueError, FileNotFoundError) as e:
        print(f"dimgestor distill: {e}")
        return 2
    print(f"student saved: {last}")
    return 0

