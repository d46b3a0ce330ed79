"""A worker's metrics in the Prometheus text format (`/metrics`), written with `prometheus_client`.

Each server owns its `CollectorRegistry` (never the library's global one), so several servers in one process
(tests, an embedding program) keep their own counts. Two kinds of metric:
- counted where it happens: sessions started and refused (`streamer.ws`), each inference call's compute time
  and batch size (the scheduler calls `began` / `ended` around it, `streamer.scheduling`), each window's
  end-to-end latency (`streamer.sessions.Session.on_window`);
- read at scrape time from the live objects (`_Live`): streams and clients, frames sent and dropped per sink
  (each sink's own cumulative counters), queue depths, the real-time factor and readiness
  (`streamer.health`).

Names follow Prometheus' conventions: `dimgestor_` prefix, `_total` counters, `_seconds` histograms with
buckets from 1 ms to 10 s (a window computes in 1-1000 ms; the tail catches stalls).
"""

from __future__ import annotations

from typing import Callable

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

from streamer.health import Readiness

SECONDS_BUCKETS = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256)

FrameCounts = Callable[[], tuple[int, int | None]]  # () -> (frames sent, frames dropped or None: not counted)


class ServerMetrics:
    """One worker's metrics: its registry, the hooks the serving code calls, and the live values it reads."""

    def __init__(self, readiness: Readiness | None = None):
        self.readiness = readiness if readiness is not None else Readiness()
        self.registry = r = CollectorRegistry()
        self.sessions_started = Counter("dimgestor_sessions_started", "Client audio sessions started", registry=r)
        self.faces_withheld = Counter("dimgestor_faces_withheld", "Client audio sessions admitted without the face "
                                      "they asked, at capacity (--faces-beyond-capacity no-face)", registry=r)
        self.sessions_handed_over = Counter("dimgestor_sessions_handed_over",
                                            "Client sessions saved to the state store when the worker stopped",
                                            registry=r)
        self.sessions_resumed = Counter("dimgestor_sessions_resumed",
                                        "Client sessions resumed from the state store", registry=r)
        self.sessions_saved = Counter("dimgestor_sessions_saved",
                                      "Periodic saves of client sessions to the state store (--save-state-every)",
                                      registry=r)
        self.states_put = Counter("dimgestor_states_put", "Session states written to the state store (periodic "
                                  "saves and hand-overs)", registry=r)
        self.state_bytes_put = Counter("dimgestor_state_bytes_put", "Bytes of session states written to the state "
                                       "store", registry=r)
        self.state_puts_refused = Counter(
            "dimgestor_state_puts_refused", "Session states the store refused: too_large (over --state-max-bytes) "
            "or spent (its token was already taken or its session ended)", ["reason"], registry=r)
        self.sessions_refused = Counter(
            "dimgestor_sessions_refused", "Client audio refused a session: busy (--max-sessions reached), "
            "capacity (one more would not keep real time: streamer.capacity), draining (shutting down) or "
            "audio_disabled (--no-client-audio)", ["reason"], registry=r)
        self.compute_seconds = Histogram(
            "dimgestor_window_compute_seconds", "Compute time of one inference call: one batched forward (the "
            "windows in it share it) or one solo window", buckets=SECONDS_BUCKETS, registry=r)
        self.batch_windows = Histogram(
            "dimgestor_batch_windows", "Windows (streams) per inference call", buckets=BATCH_BUCKETS, registry=r)
        self.latency_seconds = Histogram(
            "dimgestor_latency_seconds", "End to end, per window: its last audio sample received -> its frames "
            "handed to the sinks (a client's queue)", buckets=SECONDS_BUCKETS, registry=r)
        self.busy_seconds = Counter(
            "dimgestor_inference_busy_seconds", "Inference thread time spent computing, by work: realtime "
            "(counts against /readyz) or backlog", ["work"], registry=r)
        self.streams: list[Callable[[], int]] = []  # each () -> live streams of one owner (WsServer, the source)
        self.clients: Callable[[], int] = lambda: 0
        self.sinks: dict[str, FrameCounts] = {}
        self.queues: dict[str, Callable[[], float]] = {}  # gauge name -> () -> value (see _Live)
        self.store = None  # the worker's `streamer.store_link.StoreLink`, if it has a state store
        r.register(_Live(self))
        ProcessCollector(registry=r)  # process_cpu_seconds_total, process_resident_memory_bytes, ... (Linux)

    # ---- hooks of the serving code ---------------------------------------------------------------

    def began(self, realtime: bool) -> None:
        """An inference call starts on this thread (real-time work or a backlog)."""
        self.readiness.load.began(realtime)

    def ended(self, windows: int) -> None:
        """The call on this thread is done; it computed `windows` windows (0: another job, a stream's finish)."""
        took, realtime = self.readiness.load.ended()
        self.busy_seconds.labels("realtime" if realtime else "backlog").inc(took)
        if windows:
            self.compute_seconds.observe(took)
            self.batch_windows.observe(windows)

    def window_done(self, latency_s: float) -> None:
        self.latency_seconds.observe(latency_s)

    def refused(self, reason: str) -> None:
        self.sessions_refused.labels(reason).inc()

    # ---- exposition ------------------------------------------------------------------------------

    def exposition(self) -> tuple[bytes, str]:
        """(body, content type) of `/metrics`: the text format every Prometheus parses."""
        return generate_latest(self.registry), CONTENT_TYPE_LATEST


class _Live(Collector):
    """The values read from the live objects at each scrape."""

    def __init__(self, m: ServerMetrics):
        self.m = m

    def collect(self):
        m = self.m
        yield GaugeMetricFamily("dimgestor_streams", "Live streams: client audio sessions running (flushes "
                                "included) and the server's own source", value=sum(f() for f in m.streams))
        yield GaugeMetricFamily("dimgestor_clients", "Connected WebSocket clients", value=m.clients())
        sent = CounterMetricFamily("dimgestor_frames_sent", "Frames sent, per sink (ws: frame messages handed "
                                   "to a client's socket, each client counted)", labels=["sink"])
        dropped = CounterMetricFamily("dimgestor_frames_dropped", "Frames dropped, per sink (ws: broadcast frames "
                                      "pushed out of a slow client's queue; vmc: late or pushed out)", labels=["sink"])
        for name, counts in m.sinks.items():
            n_sent, n_dropped = counts()
            sent.add_metric([name], n_sent)
            if n_dropped is not None:
                dropped.add_metric([name], n_dropped)
        yield sent
        yield dropped
        for name, value in m.queues.items():
            what, unit = QUEUES[name]
            yield GaugeMetricFamily(name, what, value=value(), unit=unit)
        load = m.readiness.load
        yield GaugeMetricFamily("dimgestor_realtime_factor", f"Real-time factor of the batch: inference seconds "
                                f"spent on real-time work per second of wall time and thread, over the last "
                                f"{load.window_s:g} s (under 1: keeps real time; /readyz fails above "
                                f"{m.readiness.max_load:g})", value=load.value())
        ready, why = m.readiness.check()
        yield GaugeMetricFamily("dimgestor_ready", "1 when /readyz answers 200", value=float(ready))
        if m.readiness.faces_left is not None and (left := m.readiness.faces_left()) is not None:
            yield GaugeMetricFamily("dimgestor_faces_left", "How many more sessions with a face this worker admits now "
                                    "(their cost learnt as it runs: streamer.capacity)", value=left)
        yield GaugeMetricFamily("dimgestor_degraded", "1 when /readyz says degraded (ready, but the state store "
                                "does not answer: no hand-over)", value=float(why.startswith("degraded")))
        if m.store is not None:
            yield from _store_metrics(m.store)


def _store_metrics(link):
    """The state store as its link (`streamer.store_link`) sees it: up or not, calls by outcome, delays."""
    yield GaugeMetricFamily("dimgestor_store_up", "1 while the state store answers; 0 while it is taken as down "
                            "(calls fail at once, pinged until it answers)", value=float(link.up))
    yield GaugeMetricFamily("dimgestor_store_queue_calls", "State store calls waiting for the store's thread",
                            value=link.queued)
    yield CounterMetricFamily("dimgestor_store_outages", "Times the state store was found down (a failed or "
                              "timed-out call or ping)", value=link.outages)
    counts, delays = link.counts()
    calls = CounterMetricFamily("dimgestor_store_calls", "State store calls by method (put: a save, take: a "
                                "resume, touch, release, forget) and outcome: ok; refused (the store said no: a "
                                "spent token, a live session, a state too large); late (done after its caller's "
                                "deadline); failed; timeout (past its deadline); dropped "
                                "(still queued at its deadline, never run); busy (queue full); down (refused at "
                                "once while the store is down)", labels=["call", "outcome"])
    for (name, outcome), n in sorted(counts.items()):
        calls.add_metric([name, outcome], n)
    yield calls
    delayed = CounterMetricFamily("dimgestor_store_calls_delayed", "State store calls that took over 0.5 s from "
                                  "the request to the answer (queue + store), by method", labels=["call"])
    for name, n in sorted(delays.items()):
        delayed.add_metric([name], n)
    yield delayed


QUEUES = {  # the queue-depth gauges a server may register in `ServerMetrics.queues`: name -> (help, unit)
    "dimgestor_client_queue_messages": ("Messages waiting in the WebSocket clients' outgoing queues", ""),
    "dimgestor_inference_queue_jobs": ("Inference jobs waiting for the inference thread (windows, finishes)", ""),
    "dimgestor_audio_backlog_seconds": ("Client audio received and not yet inferred, all clients", "seconds"),
}
