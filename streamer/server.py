"""`streamer serve`: `build` makes the pipeline from `ServeOptions` (source, sessions, sinks), `run` drives it
(status lines, Ctrl-C) and shuts it down cleanly.

    options --build--> Pipeline: source -> session -> sinks (WebSocket, VMC, recording: `streamer.sink.Sink`)
                                 WebSocket clients' own audio -> make_session() -> that client
"""

from __future__ import annotations

import asyncio
import functools
import math
import os
import signal
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, AsyncIterator, Callable

from dimgestor.streaming.stream import MODEL_SPEAKER
from streamer.face import ServeFace
from streamer.frames import Frame
from streamer.handover import open_store
from streamer.health import Readiness, RealtimeLoad
from streamer.metrics import ServerMetrics
from streamer.options import ServeError, ServeOptions
from streamer.scheduling import BatcherPool, RankedScheduler, StreamBatcher
from streamer.sessions import Session
from streamer.sink import Sink
from streamer.sources import AudioChunk, MicSource, WavSource, open_source

if TYPE_CHECKING:
    from dimgestor.export.onnx_stream import OnnxModel
    from dimgestor.streaming.checkpoint import Bundle
    from streamer.face_process import FaceProcess
    from streamer.ws import WsServer

__all__ = ["Pipeline", "ServeError", "ServeOptions", "build", "read_state_secret", "read_token", "run", "serve"]
TOKEN_ENV = "STREAMER_TOKEN"
STATE_SECRET_ENV = "DIMGESTOR_STATE_SECRET"
# --backend onnxruntime without --onnx: the batch sizes exported (once, into the cache) beside the single-stream
# graph (each takes about as long to export as it; benchmarks/results/onnx_runtime.json's per-call table: most of
# the saving per stream is there by 4 streams a call at K = 8)
SERVE_BATCHES = (4, 8)
SIGNALS = (signal.SIGINT, signal.SIGTERM)


@dataclass
class Pipeline:
    """What `build` makes of the options; `run` drives it."""

    options: ServeOptions
    bundle: Bundle  # the model, its skeleton and feature spec
    steps: int  # DDIM steps K, and the guidance scale, as resolved against the checkpoint's defaults
    guidance: float
    source: WavSource | MicSource | None  # the server's own audio; None: --source ws
    session: Session | None  # the source's session
    make_session: Callable[..., Session]  # one more session (a WebSocket client's own audio)
    scheduler: StreamBatcher | BatcherPool | RankedScheduler  # where every session's inference runs
    sinks: list[Sink]  # where the source's frames go, in the order they open
    ws: WsServer | None = None  # the WebSocket server (also among the sinks): clients bring their own audio too
    metrics: ServerMetrics = field(default_factory=ServerMetrics)  # served by `ws` (/metrics, /readyz)
    face: ServeFace | None = None  # the face every session makes and every sink sends (None: bones only)
    face_process: FaceProcess | None = None  # where the sessions' faces are made (--face-process; None: inline)
    t0: float = field(default_factory=time.monotonic)

    @property
    def executor(self) -> StreamBatcher | BatcherPool | RankedScheduler:
        """Deprecated name of `scheduler`."""
        warnings.warn("Pipeline.executor is deprecated: use Pipeline.scheduler", DeprecationWarning, stacklevel=2)
        return self.scheduler


async def serve(options: ServeOptions) -> int:
    pipeline = build(options)
    try:
        return await run(pipeline)
    finally:
        pipeline.scheduler.shutdown(wait=False, cancel_futures=True)
        if pipeline.face_process is not None:
            pipeline.face_process.close()


# ---- build ---------------------------------------------------------------------------------------

def build(options: ServeOptions) -> Pipeline:
    """The pipeline, nothing opened yet but the source and the model (a bad device, file, checkpoint or map
    fails here, with a ServeError or SourceError that says which)."""
    from streamer.pose import HumanoidRig

    t0 = time.monotonic()
    face = _face(options)
    if face is None and options.face != "none":  # (no pocketsphinx wheel here: said, and --face none from here on)
        options = options.model_copy(update={"face": "none"})
    token = read_token(options)
    if token is not None:
        from streamer.redact import RedactTokens

        RedactTokens.add_secret(token)  # -v logs request lines: a token put in the URL path is masked there too
    state_key = read_state_secret(options)
    source = _source(options)  # fail early: before the model loads
    humanoid = _humanoid_map(options.humanoid_map)
    device = _compute_device(options)
    bundle = _load(options.checkpoint, device if options.backend == "torch" else "cpu")  # (ONNX Runtime's own)
    if options.speaker is not None:  # (ONNX Runtime: the export plays it, its vector baked in: _onnx_export)
        try:
            bundle.model.use_speaker(options.speaker)
        except ValueError as e:
            raise ServeError(f"--speaker: {e}") from None
    steps = options.steps if options.steps is not None else bundle.config.sample_steps
    guidance = options.guidance if options.guidance is not None else bundle.config.guidance
    onnx = _onnx_model(options, bundle, steps, guidance) if options.backend == "onnxruntime" else None
    scheduler = _scheduler(options.no_batch, onnx, device)
    one_blas_thread()
    metrics = _metrics(scheduler)
    admission = _admission(options, bundle, face, metrics, scheduler)
    face_process = _face_process(options, face)
    # one more session: a WebSocket client's own audio (its keyword arguments: Session's own, e.g. face=None)
    make_session = functools.partial(_session, bundle, options, scheduler, steps, guidance, onnx=onnx,
                                     state_key=state_key, face=face.options if face is not None else None,
                                     face_cost=admission.face_cost if admission is not None else None,
                                     face_process=face_process)
    session = make_session("source", on_window=metrics.window_done) if source is not None else None
    if options.state_store is not None:  # what a resumed state's values may reach, learnt now (~1 s), not on a resume
        from dimgestor.streaming import state_bounds

        state_bounds.prime((session or make_session()).stream)
    if session is not None:
        metrics.streams.append(lambda: int(not session.stats.ended))
    sk = bundle.skeleton
    target = _target(options, sk)
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, humanoid) if target is None else target.humanoid_rig()
    ws = None if options.no_ws else _ws(options, bundle, rig, source, session, make_session, token, metrics, face,
                                        target, admission)
    vmc, recording = _vmc(options, rig, face, target), _recording(options, bundle, source, face, target)
    if vmc is not None:
        metrics.sinks["vmc"] = lambda: (vmc.sent, vmc.dropped)
    if recording is not None:  # (frames on disk; after a write error the rest are not counted anywhere)
        metrics.sinks["record"] = lambda: (recording.recorder.frames if recording.recorder else 0, None)
    sinks = [s for s in (ws, vmc, recording) if s is not None]
    return Pipeline(options, bundle, steps, guidance, source, session, make_session, scheduler, sinks, ws, t0=t0,
                    metrics=metrics, face=face, face_process=face_process)


def _face(options: ServeOptions) -> ServeFace | None:
    """--face, --smile and --seed, resolved once into the face every session, sink and client is given; None: bones
    only (--face none, or no listener on this machine: said once, with what to do)."""
    from dimgestor.face import FaceOptions
    from dimgestor.face.listener import unavailable as face_unavailable

    if options.face == "none":
        return None
    if "pocketsphinx" in options.face_listener and (why := face_unavailable()) is not None:
        print(f"dimgestor: no face, bones only: --face-listener {options.face_listener}: {why}", file=sys.stderr,
              flush=True)
        return None
    return ServeFace(options.face, FaceOptions(seed=options.seed, smile=options.smile,
                                               listener=options.face_listener))


def _face_process(options: ServeOptions, face: ServeFace | None) -> FaceProcess | None:
    """--face-process: the child process the sessions' faces are made in, started now and waited for (its imports
    take a few seconds: not in a first client's window). None without the flag, or without a face."""
    if not options.face_process or face is None:
        return None
    from streamer.face_process import FaceProcess, FaceProcessEnded

    process = FaceProcess()
    try:
        process.ready()
    except FaceProcessEnded as e:
        process.close()
        raise ServeError(f"--face-process: {e}") from None
    return process


def _source(options: ServeOptions):
    source = open_source(options.source, device=options.device_id, realtime=not options.fast, loop=options.loop,
                         rate=options.rate, gain_db=options.gain, gate_dbfs=options.gate)
    if isinstance(source, MicSource):
        source.warn = lambda text: print(f"dimgestor: {text}", file=sys.stderr, flush=True)
    return source


def _target(options: ServeOptions, skeleton):
    """The rig the frames are sent on (--target), or None: the model's skeleton."""
    if options.target is None:
        return None
    from dimgestor.retarget import RigError
    from dimgestor.retarget.names import MapError
    from streamer.pose import TargetPose

    try:
        return TargetPose.from_file(skeleton, options.target, options.target_map)
    except (RigError, MapError) as e:
        raise ServeError(f"--target: {e}") from None


def _humanoid_map(path: str | None):
    from streamer.pose import HumanoidMapError, load_humanoid_map

    try:
        return load_humanoid_map(path)
    except HumanoidMapError as e:
        raise ServeError(str(e)) from None


def _compute_device(options: ServeOptions) -> str:
    """--device, checked before anything loads: "cpu", or a CUDA GPU this machine has (and, with --backend
    onnxruntime, an ONNX Runtime with the CUDA provider); else one line saying why not."""
    device = options.compute_device
    if device == "cpu":
        return device
    import torch

    if not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, but no GPU visible"
        raise ServeError(f"--device {device}: no NVIDIA GPU here (torch {torch.__version__}: {build}); serve on the "
                         "CPU (leave out --device), or install torch's CUDA build on a machine with one "
                         "(docs/install.md)")
    count, index = torch.cuda.device_count(), int(device.partition(":")[2] or 0)
    if index >= count:
        raise ServeError(f"--device {device}: this machine has {count} GPU{'s' * (count != 1)} (cuda:0.."
                         f"cuda:{count - 1})")
    if options.backend == "onnxruntime":
        import onnxruntime as ort

        if "CUDAExecutionProvider" not in ort.get_available_providers():
            raise ServeError(f"--device {device} --backend onnxruntime: this ONNX Runtime has no CUDA provider "
                             "(the onnxruntime package is CPU-only: install onnxruntime-gpu in its place)")
    return device


def _load(checkpoint: str | None, device: str = "cpu"):
    from dimgestor.streaming.checkpoint import CheckpointError, load_checkpoint

    try:
        return load_checkpoint(checkpoint, device=device)
    except (CheckpointError, OSError, ValueError) as e:
        raise ServeError(f"cannot load {checkpoint or 'the embedded default model'}: {e}") from None


def _scheduler(no_batch: bool, onnx: OnnxModel | None = None, device: str = "cpu"):
    if no_batch:
        return RankedScheduler(max_workers=min(4, os.cpu_count() or 1), thread_name_prefix="infer")
    if onnx is not None:  # the due windows of every session as calls of the export's batched graphs
        return onnx_batchers(onnx, onnx_lanes() if device == "cpu" else 1)  # (a GPU: one lane)
    import torch

    # one batched forward per sampler step for every session with a window due, all on the batcher's thread
    torch.set_num_threads(inference_threads())
    return StreamBatcher()


def one_blas_thread() -> None:
    """numpy's BLAS (OpenBLAS in numpy's and scipy's wheels) on the calling thread alone, for the whole process. A
    served window's products outside torch (the face's listener, a batch's faces together) are small: a pool of
    BLAS threads brings them little, and its threads spin after each product on the cores the inference thread and
    the event loop need; where the machine is busy, a product waits for its pool's threads to get a core
    (benchmarks/README.md, "numpy's BLAS threads"). torch's own threads (OpenMP) are set apart, by
    `inference_threads`."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")


def onnx_batchers(onnx: OnnxModel, lanes: int) -> BatcherPool:
    """`lanes` StreamBatchers on ONNX Runtime, each batching its share of the sessions as calls of the export's
    graphs on its own one-thread sessions: a batched call of this graph keeps one core busy, whatever ONNX
    Runtime's intra-op threads (`BatcherPool`)."""
    from dimgestor.export.onnx_batch import BatchRunner, push_many

    return BatcherPool([StreamBatcher(push_many=functools.partial(push_many, BatchRunner.of(onnx, 1)),
                                      thread_name=f"infer-batch-{i}") for i in range(max(1, lanes))])


def onnx_lanes() -> int:
    """`--backend onnxruntime`'s batchers on the CPU: OMP_NUM_THREADS when set (as `inference_threads`), else one a
    core. A lane's call runs in ONNX Runtime without Python's lock, so the event loop still gets its share of the
    cores; on 2 cores one lane kept far fewer streams than two (benchmarks/README.md, "ONNX Runtime's lanes")."""
    return _given_threads() or max(1, os.cpu_count() or 1)


def inference_threads() -> int:
    """Torch threads of the batched inference: OMP_NUM_THREADS when set (several workers on one machine each
    take their share, docs/deploy.md; torch.set_num_threads would otherwise override it), else every core but
    one, which stays with the event loop (poses, sockets, VMC)."""
    return _given_threads() or max(1, (os.cpu_count() or 1) - 1)


def _given_threads() -> int | None:
    """OMP_NUM_THREADS when it is a positive whole number, else None."""
    given = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(given) if given.isdigit() and int(given) > 0 else None


def _metrics(scheduler: StreamBatcher | BatcherPool | RankedScheduler) -> ServerMetrics:
    """The worker's metrics, fed by every inference call of `scheduler` (its real-time load decides /readyz)."""
    metrics = ServerMetrics(Readiness(RealtimeLoad(threads=scheduler.workers)))
    scheduler.observer = metrics
    metrics.queues["dimgestor_inference_queue_jobs"] = scheduler.queued_jobs
    return metrics


def _admission(options: ServeOptions, bundle, face: ServeFace | None, metrics: ServerMetrics, scheduler):
    """Who is admitted beyond the seats (`streamer.capacity`): none while the worker is not ready, a face only while
    the faces fit; a face's cost measured now (~0.1 s) and learnt as the sessions make them."""
    if options.no_ws or options.no_client_audio:
        return None
    from streamer.capacity import Admission, FaceCost

    cost = None
    if face is not None:
        cost = FaceCost()
        lookahead = math.floor(min(bundle.model.lookahead_s, 0.3) * 100 + 1e-6) / 100  # as a session's face
        cost.measure(face.options, bundle.feature_spec.fps, lookahead)
    return Admission(metrics.readiness, cost, lanes=scheduler.workers,
                     without_face=options.faces_beyond_capacity == "no-face")


def _session(bundle, options: ServeOptions, scheduler, steps: int, guidance: float, name: str = "client",
             onnx: OnnxModel | None = None, speaker=MODEL_SPEAKER, **settings) -> Session:
    """A session of this server's model, steps and options; `speaker`: the speaker it plays (a name, None for none
    in particular; MODEL_SPEAKER: the server's --speaker); `settings`: Session's own keyword arguments (face,
    face_cost, state_key, clock, on_window, on_boundary)."""
    if onnx is not None:  # --backend onnxruntime: the exported frame step on ONNX Runtime (one session for all)
        from dimgestor.features import PoseDecoder

        if speaker is not MODEL_SPEAKER and speaker != bundle.model.speaker:  # (a client's hello was refused it)
            raise ValueError(f"speaker {speaker!r}: the ONNX Runtime backend plays {bundle.model.speaker!r} only")

        stream = onnx.stream(seed=options.seed, smoothing=options.smoothing, lookahead_s=bundle.model.lookahead_s)
        decoder = PoseDecoder(bundle.skeleton, bundle.feature_spec, root=options.root, tether_s=options.tether_s)
        return Session(stream, decoder, bundle.denormalize, bundle.feature_spec.fps, window_ms=options.window_ms,
                       scheduler=scheduler, name=name, **settings)
    return Session.from_bundle(bundle, steps=steps, seed=options.seed, smoothing=options.smoothing,
                               root=options.root, tether_s=options.tether_s, guidance=guidance, speaker=speaker,
                               window_ms=options.window_ms, scheduler=scheduler, name=name, **settings)


def _onnx_model(options: ServeOptions, bundle, steps: int, guidance: float) -> OnnxModel:
    """--backend onnxruntime: the export loaded once for every session (`_onnx_export`)."""
    from dimgestor.export.onnx_stream import OnnxModel

    return OnnxModel.load(_onnx_export(options, bundle, steps, guidance), device=options.compute_device)


def _onnx_export(options: ServeOptions, bundle, steps: int, guidance: float) -> str:
    """--backend onnxruntime: the --onnx folder (checked against the checkpoint, K and guidance), or the
    checkpoint's export in the per-user cache (`dimgestor.export.onnx_cache`: exported on the first start, reused after)."""
    from dimgestor.export.onnx_export import check_export
    from dimgestor.export.onnx_stream import load_manifest

    if options.onnx is not None:
        try:
            manifest = load_manifest(options.onnx)
            check_export(manifest, bundle)
        except (OSError, ValueError, KeyError) as e:
            raise ServeError(f"--onnx {options.onnx}: {e}") from None
        sampler = manifest["sampler"]
        if (options.steps is not None and options.steps != sampler["steps"]
                or options.guidance is not None and options.guidance != sampler["guidance"]):
            raise ServeError(f"--onnx {options.onnx} was exported with K={sampler['steps']} and guidance "
                             f"{sampler['guidance']:g}: pass those (or export again)")
        return options.onnx
    from dimgestor.export.onnx_cache import cached_export

    batches, model = () if options.no_batch else SERVE_BATCHES, options.checkpoint or "the embedded model"
    try:
        return str(cached_export(bundle, steps, guidance, batches=batches, root=options.onnx_cache,
                                 log=lambda text: print(f"dimgestor: {text}", file=sys.stderr, flush=True)))
    except OSError as e:
        raise ServeError(f"--backend onnxruntime: cannot keep the export of {model}: {e} (a writable folder: "
                         "--onnx-cache DIR)") from None
    except ValueError as e:
        raise ServeError(f"--backend onnxruntime: cannot export {model}: {e}") from None


def _ws(options: ServeOptions, bundle, rig, source, session: Session | None, make_session, token: str | None,
        metrics: ServerMetrics, face: ServeFace | None, target=None, admission=None):
    from streamer import protocol as P
    from streamer.ws import Attached, WsConfig, WsServer

    sk, fps = bundle.skeleton, bundle.feature_spec.fps
    fps = int(fps) if float(fps).is_integer() else fps
    lookahead = (session or make_session()).lookahead_s
    info = P.SkeletonInfo.from_skeleton(sk) if target is None else target.skeleton_info()
    hello = P.hello(info, rig.mapping(info.names), fps, lookahead,
                    accepts_audio=not options.no_client_audio, window_ms=options.window_ms,
                    source="ws" if source is None else "mic" if options.source == "mic" else "file",
                    **({"source_audio": {"rate": P.AUDIO_RATE, "format": "pcm16", "channels": 1}}
                       if isinstance(source, WavSource) else {}),
                    **({"speakers": P.speakers_hello(bundle.config.speakers, bundle.model.speaker,
                                                     fixed=options.backend == "onnxruntime")}
                       if bundle.config.speakers else {}))
    also = [(options.http[0] or options.ws[0], options.http[1])] if options.http is not None else []
    config = WsConfig(options.ws[0], options.ws[1], also=tuple(also), token=token, origins=tuple(options.allow_origin),
                      max_sessions=options.max_sessions, ping_interval=options.ping_interval or None,
                      ping_timeout=options.ping_timeout, serve_metrics=not options.no_metrics,
                      save_every_s=options.save_state_every, face=face.names if face is not None else None)
    attached = Attached(metrics=metrics, store=open_store(options.state_store, options.state_ttl,
                                                          options.state_max_bytes),
                        pose=target, skeleton=sk, broadcast_stats=session.stats if session else None,
                        source_dropped_s=(lambda: source.dropped_s) if isinstance(source, MicSource) else None,
                        admission=admission)
    return WsServer(config, hello, None if options.no_client_audio else make_session, attached)


def _vmc(options: ServeOptions, rig, face: ServeFace | None, target=None):
    if options.osc is None:
        return None
    from streamer.vmc import VmcSink, face_channels

    scale = 0.01 if target is None else target.metres_per_unit
    return VmcSink(options.osc[0], options.osc[1], rig, scale=scale, pace=not options.fast,
                   jitter_s=_vmc_jitter_ms(options) / 1000, options=options.vmc(),
                   channels=face_channels(face.names if face is not None else "none"), pose=target)


def _vmc_jitter_ms(options: ServeOptions) -> float:
    """The VMC jitter buffer: one window unless set. It absorbs how much later than usual a window's frames come,
    mostly the variation of its inference time, which grows with the window and stays below one window while the
    server keeps real time (benchmarks/latency.py: the fixed 250 ms it replaces was 150 ms of waiting at 100 ms
    windows)."""
    return options.window_ms if options.vmc_jitter_ms is None else options.vmc_jitter_ms


def _recording(options: ServeOptions, bundle, source, face: ServeFace | None, target=None):
    if not options.record or source is None:
        return None
    from streamer.record import RecordingSink

    suffix = Path(options.record).suffix.lower()
    fits = options.target is not None and (suffix == ".glb" or suffix in (".bvh", ".npz")
                                           and Path(options.target).suffix.lower() == ".bvh")
    if fits and suffix == ".npz" and target is not None:  # a take is on SMPL-X: the target's only if it is SMPL-X
        from dimgestor import smplx

        fits = target.file.rig.skeleton is not None and smplx.is_smplx(target.file.rig.skeleton)
    return RecordingSink(options.record, bundle.skeleton, bundle.feature_spec, root=options.root,
                         tether_s=options.tether_s, face=face is not None,
                         target=target.file if fits and target is not None else None)  # (read once: _target)


def read_token(options) -> str | None:
    """The WebSocket token from --token-file, --token or $STREAMER_TOKEN (in that order); never empty."""
    if options.token_file:
        try:
            token = Path(options.token_file).read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as e:
            raise ServeError(f"--token-file {options.token_file}: {getattr(e, 'strerror', None) or e}") from None
        where = f"--token-file {options.token_file}"
    elif options.token is not None:
        token, where = options.token, "--token"
    elif TOKEN_ENV in os.environ:
        token, where = os.environ[TOKEN_ENV], f"${TOKEN_ENV}"
    else:
        return None
    if not token.strip():
        raise ServeError(f"{where} is empty: an empty token would lock every client out (give a real one, or none)")
    if any(c.isspace() or not c.isprintable() for c in token):
        raise ServeError(f"{where} contains spaces or control characters (clients pass it in a URL)")
    return token


def read_state_secret(options) -> bytes | None:
    """The secret that seals saved states, from --state-secret-file or $DIMGESTOR_STATE_SECRET (surrounding
    whitespace ignored; never empty), only with a --state-store; it is masked in every log line."""
    if options.state_store is None:
        return None
    if options.state_secret_file:
        try:
            secret = Path(options.state_secret_file).read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as e:
            raise ServeError(f"--state-secret-file {options.state_secret_file}: "
                             f"{getattr(e, 'strerror', None) or e}") from None
        where = f"--state-secret-file {options.state_secret_file}"
    elif STATE_SECRET_ENV in os.environ:
        secret, where = os.environ[STATE_SECRET_ENV].strip(), f"${STATE_SECRET_ENV}"
    else:
        return None
    if not secret:
        raise ServeError(f"{where} is empty: give the secret every worker of the cluster shares (or none)")
    from streamer.redact import RedactTokens

    RedactTokens.add_secret(secret)
    return secret.encode()


# ---- run -----------------------------------------------------------------------------------------

async def run(p: Pipeline) -> int:
    """Open the sinks, stream the source until it ends or Ctrl-C / SIGTERM / --max-seconds, close them all."""
    await _open(p.sinks)
    print(_banner(p), file=sys.stderr, flush=True)
    stop, loop = asyncio.Event(), asyncio.get_running_loop()

    def on_signal() -> None:  # from now on /readyz says 503: a balancer sends new sessions elsewhere
        p.metrics.readiness.draining = True
        stop.set()

    for sig in SIGNALS:
        loop.add_signal_handler(sig, on_signal)
    if p.options.max_seconds is not None:
        loop.call_later(p.options.max_seconds, stop.set)
    status = asyncio.create_task(_report(p))
    try:
        if p.session is not None:
            await _stream(p, stop)
        else:
            await stop.wait()
    finally:
        status.cancel()
        for sig in SIGNALS:
            loop.remove_signal_handler(sig)
        # Ctrl-C: stop now; source end: each sink plays out its tail (all at once, each within its bound)
        await asyncio.gather(*(sink.close(drain=not stop.is_set()) for sink in p.sinks))
        print(_status_line(p), file=sys.stderr, flush=True)
    return 0


async def _open(sinks: list[Sink]) -> None:
    """Open every sink in order; if one fails, close those already open (a recording, opened last, then
    never replaces an old file) and say why."""
    opened: list[Sink] = []
    try:
        for sink in sinks:
            await sink.open()
            opened.append(sink)
    except BaseException as e:
        await asyncio.gather(*(sink.close(drain=False) for sink in opened))
        if isinstance(e, OSError):
            raise ServeError(str(e)) from None
        raise


async def _stream(p: Pipeline, stop: asyncio.Event) -> None:
    """The source through its session into every sink, until the source ends or `stop`."""
    if p.options.wait_client and p.ws is not None:
        print("dimgestor: waiting for a WebSocket client before starting the source", file=sys.stderr, flush=True)
        while not p.ws.clients and not stop.is_set():
            await asyncio.sleep(0.02)
    chunks = until(p.source, stop)
    if p.ws is not None and isinstance(p.source, WavSource):
        chunks = tap(chunks, p.ws.broadcast_audio)  # viewers may ask to hear what the avatar gestures to

    def emit(frames: list[Frame]) -> None:
        for sink in p.sinks:
            sink.send(frames)

    n = await p.session.run(chunks, emit)
    print(f"dimgestor: source ended after {n} frames", file=sys.stderr)


async def until(source, stop: asyncio.Event) -> AsyncIterator[AudioChunk]:
    """The source's chunks until `stop` is set (Ctrl-C): the session then flushes like at a file's end."""
    it = source.__aiter__()
    stopper = asyncio.create_task(stop.wait())
    try:
        while not stop.is_set():
            nxt = asyncio.ensure_future(it.__anext__())
            await asyncio.wait({nxt, stopper}, return_when=asyncio.FIRST_COMPLETED)
            if stop.is_set():  # checked first: a source that always has data must not outrun Ctrl-C
                nxt.cancel()
                await asyncio.gather(nxt, return_exceptions=True)
                return
            try:
                chunk = nxt.result()
            except StopAsyncIteration:
                return
            yield chunk
    finally:
        stopper.cancel()
        if hasattr(it, "aclose"):
            await it.aclose()


async def tap(chunks: AsyncIterator[AudioChunk], sink) -> AsyncIterator[AudioChunk]:
    """The chunks unchanged, each also handed to `sink(t_start, samples)` as the session takes it."""
    async for chunk in chunks:
        sink(chunk.t_start, chunk.samples)
        yield chunk


# ---- what it prints ------------------------------------------------------------------------------

def _banner(p: Pipeline) -> str:
    o, source = p.options, p.source
    what = (f"microphone {source.name!r} at {source.rate} Hz" if isinstance(source, MicSource)
            else "WebSocket clients' audio only" if source is None
            else f"demo clip {source.path.name}" if o.source == "demo" else f"file {o.source}")
    session = p.session or p.make_session()
    smoother = session.stream.smoother
    smooth = f"smoothing {smoother.min_cutoff_hz:g} Hz" if smoother else "no smoothing"
    smooth += f", root {o.root}" + (f" ({o.tether_s:g} s)" if o.root == "tether" else "")
    fps = p.bundle.feature_spec.fps
    lines = [f"model {o.checkpoint or 'default (embedded)'}, K={p.steps}, seed={o.seed}, "
             + (f"guidance {p.guidance:g}, " if p.guidance != 1.0 else "") + f"{smooth}, "
             f"{int(fps) if float(fps).is_integer() else fps} fps, window {o.window_ms} ms, "
             f"lookahead {session.lookahead_s * 1000:.0f} ms"
             + (", backend onnxruntime" if o.backend == "onnxruntime" else "")
             + (f", on {o.compute_device}" if o.compute_device != "cpu" else "") + f"; source: {what}"]
    lines += [line for sink in p.sinks for line in sink.describe().splitlines()]
    if o.state_store is not None:
        lines.append("saved sessions sealed with the workers' shared secret" if session.state_key else
                     "saved sessions sealed with SHA-256 only (no --state-secret-file: corruption is detected, "
                     "forgery is not)")
    if o.http is not None:
        lines.append(f"--http is deprecated: the viewer is served on the WebSocket port ({p.ws.viewer_urls[0]}); "
                     f"--http still serves it, and the WebSocket, on port {p.ws.addresses[-1][1]} too")
    return "\n".join(f"dimgestor: {line}" for line in lines)


async def _report(p: Pipeline) -> None:
    while p.options.status_every > 0:
        await asyncio.sleep(p.options.status_every)
        print(_status_line(p), file=sys.stderr, flush=True)


def _status_line(p: Pipeline) -> str:
    parts = [f"[dimgestor {time.monotonic() - p.t0:6.1f}s]"]
    if p.session is not None:
        st = p.session.stats
        parts += [f"audio {st.audio_s:6.1f}s", f"frames {st.frames}", f"latency {st.latency_ms:5.0f}ms",
                  f"rtf {st.rtf:.2f}"]
    if isinstance(p.scheduler, (StreamBatcher, BatcherPool)):
        parts += [text for text in (p.scheduler.stats.describe(), p.scheduler.cost.describe()) if text]
    parts += [text for text in (sink.status() for sink in p.sinks) if text]
    if isinstance(p.source, MicSource):
        parts += [p.source.meter.describe(), f"mic dropped {p.source.dropped_s:.1f}s"]
    return " | ".join(parts)
