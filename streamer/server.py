"""`streamer serve`: wire a source, the model and the sinks together, report status, shut down cleanly."""

from __future__ import annotations

import asyncio
import os
import signal
import sys
import time
from pathlib import Path
from typing import AsyncIterator

from streamer.engine import Frame, RankedExecutor, Session, StreamBatcher
from streamer.sources import AudioChunk, MicSource, WavSource, open_source


class ServeError(RuntimeError):
    """A configuration problem found before serving (bad checkpoint, map, record path...)."""


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


def _load(args):
    from dimgestor.checkpoint import CheckpointError, load_checkpoint

    try:
        return load_checkpoint(args.checkpoint)
    except (CheckpointError, OSError, ValueError) as e:
        where = args.checkpoint or "the embedded default model"
        raise ServeError(f"cannot load {where}: {e}") from None


def _status_line(session: Session | None, ws, vmc, source, t0: float, executor=None) -> str:
    parts = [f"[streamer {time.monotonic() - t0:6.1f}s]"]
    if session is not None:
        st = session.stats
        parts += [f"audio {st.audio_s:6.1f}s", f"frames {st.frames}", f"latency {st.latency_ms:5.0f}ms",
                  f"rtf {st.rtf:.2f}"]
    if isinstance(executor, StreamBatcher):
        parts.append(executor.stats.describe())
    if ws is not None:
        parts += [f"clients {len(ws.clients)}", f"dropped {sum(c.dropped for c in ws.clients)}",
                  f"own sessions {sum(1 for c in ws.clients if c.session is not None)}"]
    if vmc is not None:
        parts.append(f"osc sent {vmc.sent} dropped {vmc.dropped}")
    if isinstance(source, MicSource):
        parts += [source.meter.describe(), f"mic dropped {source.dropped_s:.1f}s"]
    return " | ".join(parts)


def _vmc_options(args):
    """The --vmc-* flags -> (VmcOptions, jitter seconds), or a ServeError naming the bad one."""
    from streamer.vmc import VmcOptions

    opt = lambda name, default: getattr(args, f"vmc_{name}", default)  # noqa: E731 (a Namespace from tests may lack them)
    if not 0 <= opt("jitter_ms", 250) <= 5000:
        raise ServeError(f"--vmc-jitter-ms must be in 0..5000, got {opt('jitter_ms', 250)}")
    try:
        return VmcOptions(opt("positions", "hips"), opt("hips_height", None), tuple(opt("root", (0.0, 0.0, 0.0, 0.0))),
                          opt("bones", "all"), opt("max_bytes", 0)), opt("jitter_ms", 250) / 1000
    except ValueError as e:
        raise ServeError(f"--osc: {e}") from None


TOKEN_ENV = "STREAMER_TOKEN"


def read_token(args) -> str | None:
    """The WebSocket token from --token-file, --token or $STREAMER_TOKEN (in that order); never empty."""
    if getattr(args, "token_file", None):
        try:
            token, where = Path(args.token_file).read_text(encoding="utf-8").strip(), f"--token-file {args.token_file}"
        except (OSError, UnicodeDecodeError) as e:
            raise ServeError(f"--token-file {args.token_file}: {getattr(e, 'strerror', None) or e}") from None
    elif args.token is not None:
        token, where = args.token, "--token"
    elif TOKEN_ENV in os.environ:
        token, where = os.environ[TOKEN_ENV], f"${TOKEN_ENV}"
    else:
        return None
    if not token.strip():
        raise ServeError(f"{where} is empty: an empty token would lock every client out (give a real one, or none)")
    if any(c.isspace() or not c.isprintable() for c in token):
        raise ServeError(f"{where} contains spaces or control characters (clients pass it in a URL)")
    return token


async def serve(args) -> int:
    from streamer import protocol as P
    from streamer.pose import HumanoidMapError, HumanoidRig, load_humanoid_map

    t0 = time.monotonic()
    if args.window_ms < 10 or args.window_ms > 5000:
        raise ServeError(f"--window-ms must be in 10..5000, got {args.window_ms}")
    if not 1 <= getattr(args, "max_sessions", 32) <= 4096:
        raise ServeError(f"--max-sessions must be in 1..4096, got {args.max_sessions}")
    if args.steps is not None and args.steps < 1:
        raise ServeError(f"--steps must be >= 1, got {args.steps}")
    guidance = getattr(args, "guidance", None)  # a Namespace from tests may lack it
    if guidance is not None:
        from dimgestor.diffusion import check_guidance
        try:
            check_guidance(guidance)
        except ValueError as e:
            raise ServeError(f"--guidance: {e}") from None
    if not getattr(args, "tether_s", 5.0) > 0:
        raise ServeError(f"--tether-s must be > 0, got {args.tether_s}")
    root = dict(root=getattr(args, "root", "free"), tether_s=getattr(args, "tether_s", 5.0))
    from dimgestor.stream import smoothing_from_flag
    try:
        smoothing = smoothing_from_flag(getattr(args, "smooth", None))
    except ValueError as e:
        raise ServeError(str(e)) from None
    from streamer.request_checks import allowed_origin

    bad = [o for o in (getattr(args, "allow_origin", None) or []) if allowed_origin(o) is None]
    if bad:
        raise ServeError(f"--allow-origin {bad[0]!r} is not an origin (scheme://host[:port], e.g. "
                         f"http://myapp.example:3000, or '*')")
    if args.no_ws and args.http is not None:
        raise ServeError("--http serves the viewer from the WebSocket server (drop --no-ws)")
    if args.no_ws and args.source == "ws":
        raise ServeError("--source ws needs the WebSocket server (drop --no-ws)")
    if args.record and not Path(args.record).resolve().parent.is_dir():
        raise ServeError(f"--record {args.record}: folder {Path(args.record).resolve().parent} does not exist")
    if args.record and args.source == "ws":
        raise ServeError("--record records the server's own source; --source ws has none")
    token = read_token(args)
    if token is not None:
        from streamer.redact import RedactTokens

        RedactTokens.add_secret(token)  # -v logs request lines: a token put in the URL path is masked there too
    ping_interval, ping_timeout = getattr(args, "ping_interval", 20.0), getattr(args, "ping_timeout", 20.0)
    if not (0 <= ping_interval <= 3600 and 0 < ping_timeout <= 3600):
        raise ServeError(f"--ping-interval must be in 0..3600 and --ping-timeout in (0, 3600], got "
                         f"{ping_interval} and {ping_timeout}")
    device = int(args.device) if args.device is not None and str(args.device).isdigit() else args.device
    if getattr(args, "rate", None) is not None and args.rate < 1:
        raise ServeError(f"--rate must be > 0 Hz, got {args.rate}")
    mic = dict(rate=getattr(args, "rate", None), gain_db=getattr(args, "gain", 0.0), gate_dbfs=getattr(args, "gate", None))
    source = open_source(args.source, device=device, realtime=not args.fast, loop=args.loop, **mic)  # fail early
    if isinstance(source, MicSource):
        source.warn = lambda text: print(f"streamer: {text}", file=sys.stderr, flush=True)
    try:
        humanoid = load_humanoid_map(args.humanoid_map)
    except HumanoidMapError as e:
        raise ServeError(str(e)) from None

    vmc_options, vmc_jitter_s = _vmc_options(args) if args.osc is not None else (None, 0.0)  # before the model loads
    bundle = _load(args)
    if args.steps is None:
        args.steps = bundle.config.sample_steps
    if guidance is None:
        guidance = bundle.config.guidance
    sk = bundle.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, humanoid)
    fps = bundle.feature_spec.fps
    fps = int(fps) if float(fps).is_integer() else fps
    if getattr(args, "no_batch", False):
        executor = RankedExecutor(max_workers=min(4, os.cpu_count() or 1), thread_name_prefix="infer")
    else:  # one batched forward per sampler step for every session with a window due
        import torch

        # the batcher's thread does all inference; one core stays with the event loop (poses, sockets, VMC)
        torch.set_num_threads(max(1, (os.cpu_count() or 1) - 1))
        executor = StreamBatcher()

    def make_session(name: str = "client") -> Session:
        return Session.from_bundle(bundle, steps=args.steps, seed=args.seed, smoothing=smoothing, **root,
                                   guidance=guidance, window_ms=args.window_ms, executor=executor, name=name)

    main_session = make_session("source") if source is not None else None
    lookahead = (main_session or make_session()).lookahead_s

    ws = vmc = recorder = None
    try:
        if not args.no_ws:
            from streamer.ws import WsServer

            hello = P.hello(P.SkeletonInfo.from_skeleton(sk), rig.mapping(sk.names), fps, lookahead,
                            accepts_audio=not args.no_client_audio, window_ms=args.window_ms,
                            source="ws" if source is None else "mic" if args.source == "mic" else "file",
                            **({"source_audio": {"rate": P.AUDIO_RATE, "format": "pcm16", "channels": 1}}
                               if isinstance(source, WavSource) else {}))
            also = [(args.http[0] or args.ws[0], args.http[1])] if args.http is not None else []
            ws = WsServer(args.ws[0], args.ws[1], hello, None if args.no_client_audio else make_session,
                          token=token, broadcast_stats=main_session.stats if main_session else None,
                          source_dropped_s=(lambda: source.dropped_s) if isinstance(source, MicSource) else None,
                          origins=args.allow_origin or [], also=also, max_sessions=getattr(args, "max_sessions", 32),
                          ping_interval=ping_interval or None, ping_timeout=ping_timeout)
            try:
                await ws.start()
            except OSError as e:
                where = " or ".join(f"{h}:{p}" for h, p in [tuple(args.ws), *also])
                raise ServeError(f"cannot listen on {where}: {e.strerror or e}") from None
        if args.osc is not None:
            from streamer.vmc import VmcSink

            try:
                vmc = VmcSink(args.osc[0], args.osc[1], rig, pace=not args.fast, jitter_s=vmc_jitter_s,
                              options=vmc_options)
            except OSError as e:
                raise ServeError(f"--osc {args.osc[0]}:{args.osc[1]}: {e.strerror or e}") from None
            vmc.start()
        if args.record and main_session is not None:  # opened last (a failure above leaves an old file alone)
            from streamer.record import BvhRecorder, RecordError  # but before anything streams

            try:
                recorder = BvhRecorder(args.record, sk, bundle.feature_spec, **root)
            except RecordError as e:
                raise ServeError(str(e)) from None
    except BaseException:
        if vmc:
            await vmc.close()
        if ws:
            await ws.close(within_s=0.2)
        raise

    what = {"mic": f"microphone {getattr(source, 'name', '')!r} at {getattr(source, 'rate', 0)} Hz", "ws": "WebSocket clients' audio only",
            "demo": f"demo clip {Path(getattr(source, 'path', '')).name}"}.get(args.source, f"file {args.source}")
    smoother = (main_session or make_session()).stream.smoother
    smooth_txt = f"smoothing {smoother.min_cutoff_hz:g} Hz" if smoother else "no smoothing"
    smooth_txt += f", root {root['root']}" + (f" ({root['tether_s']:g} s)" if root["root"] == "tether" else "")
    print(f"streamer: model {args.checkpoint or 'default (embedded)'}, K={args.steps}, seed={args.seed}, "
          + (f"guidance {guidance:g}, " if guidance != 1.0 else "") + f"{smooth_txt}, "
          f"{fps} fps, window {args.window_ms} ms, lookahead {lookahead * 1000:.0f} ms; source: {what}", file=sys.stderr)
    if ws:
        print(f"streamer: WebSocket  {ws.url}{'?token=...' if token else ''}  (protocol v1, docs/protocol.md)",
              file=sys.stderr)
    for url in ws.viewer_urls if ws else []:
        print(f"streamer: web viewer {url}{'  (open it as ...?token=YOUR_TOKEN)' if token else ''}", file=sys.stderr)
    if args.http is not None:
        print(f"streamer: --http is deprecated: the viewer is served on the WebSocket port ({ws.viewer_urls[0]}); "
              f"--http still serves it, and the WebSocket, on port {ws.addresses[-1][1]} too", file=sys.stderr)
    if vmc:
        print(f"streamer: VMC/OSC -> {vmc.host}:{vmc.port}", file=sys.stderr)
    if recorder:
        print(f"streamer: recording  {recorder.path}", file=sys.stderr)
    sys.stderr.flush()

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if args.max_seconds is not None:
        loop.call_later(args.max_seconds, stop.set)

    async def status_loop() -> None:
        vmc_dropped = 0
        while args.status_every > 0:
            await asyncio.sleep(args.status_every)
            line = _status_line(main_session, ws, vmc, source, t0, executor)
            if vmc is not None and vmc.dropped > vmc_dropped:  # a stall (CPU busy, process paused): say so
                line += f" | WARNING: VMC dropped {vmc.dropped - vmc_dropped} late frames (a stall: CPU busy or process paused)"
                vmc_dropped = vmc.dropped
            print(line, file=sys.stderr, flush=True)

    status = asyncio.create_task(status_loop())

    def emit(frames: list[Frame]) -> None:
        if ws:
            ws.broadcast(frames)
        if vmc:
            vmc.on_frames(frames)
        if recorder:
            recorder.on_frames(frames)

    try:
        if args.wait_client and ws is not None and main_session is not None:
            print("streamer: waiting for a WebSocket client before starting the source", file=sys.stderr, flush=True)
            while not ws.clients and not stop.is_set():
                await asyncio.sleep(0.02)
        if main_session is not None:
            chunks = until(source, stop)
            if ws is not None and isinstance(source, WavSource):
                chunks = tap(chunks, ws.broadcast_audio)  # viewers may ask to hear what the avatar gestures to
            n = await main_session.run(chunks, emit)
            if ws:
                ws.broadcast_end(n)
            print(f"streamer: source ended after {n} frames", file=sys.stderr)
        else:
            await stop.wait()
    finally:
        status.cancel()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        if recorder:
            path = recorder.close()
            if path:
                print(f"streamer: wrote {recorder.frames} frames to {path}", file=sys.stderr)
        if vmc:
            await vmc.close(drain_s=0 if stop.is_set() else 2.0)  # Ctrl-C: stop now; source end: play out the tail
        if ws:
            await ws.close(within_s=1.5)
        executor.shutdown(wait=False, cancel_futures=True)
        print(_status_line(main_session, ws, vmc, source, t0, executor), file=sys.stderr, flush=True)
    return 0
