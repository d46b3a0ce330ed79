"""The state store off the real-time path (issue 40, items 1-3): `streamer.store_link.StoreLink` runs the store's
calls on a thread of its own, bounded, with deadlines and a circuit breaker; `/readyz` and `/metrics` say so."""
import asyncio
import threading
import time

import pytest

from streamer.handover import MemoryStore
from streamer.health import Readiness
from streamer.metrics import ServerMetrics
from streamer.store_link import StoreBusy, StoreDown, StoreLink, StoreTimeout

pytestmark = pytest.mark.timeout(60)


class HangingStore(MemoryStore):
    """A MemoryStore that hangs every call (ping included) while `hang` is clear: a paused Redis."""

    def __init__(self, hang_s: float = 1.0):  # (as a Redis client's socket timeout)
        super().__init__()
        self.hang_s = hang_s
        self.running = threading.Event()
        self.running.set()
        self.threads: set[str] = set()
        self.calls = self.answered = 0  # calls that reached the store; of those, the ones it answered (or gave up)

    def _wait(self):
        self.threads.add(threading.current_thread().name)
        self.calls += 1
        try:
            if not self.running.wait(self.hang_s):
                raise TimeoutError("no answer")
        finally:
            self.answered += 1

    def put(self, token, data):
        self._wait()
        super().put(token, data)

    def take(self, token):
        self._wait()
        return super().take(token)

    def ping(self):
        self._wait()


def test_calls_run_on_the_links_own_thread_and_a_hanging_store_costs_a_call_its_deadline_then_nothing():
    store = HangingStore()
    link = StoreLink(store, ping_every_s=0.1)

    async def scenario():
        await link.call("put", "a", b"state a")
        assert await link.call("take", "a") == b"state a" and store.threads == {"store-link"}
        store.running.clear()  # paused
        t0 = time.monotonic()
        with pytest.raises(StoreTimeout, match="did not answer within 0.3 s"):
            await link.call("put", "b", b"state b", deadline_s=0.3)
        took = time.monotonic() - t0
        hung = store.calls - store.answered  # the store still holds the call: its caller did not wait for it
        assert not link.up and "degraded" in readiness.check()[1] and readiness.check()[0]
        calls = store.calls
        with pytest.raises(StoreDown, match="unreachable"):  # at once while it is down: the store is not asked
            await link.call("put", "c", b"state c")
        asked = store.calls - calls
        store.running.set()  # it answers again: the link's ping sees it
        for _ in range(100):
            if link.up:
                break
            await asyncio.sleep(0.05)
        assert link.up and readiness.check()[1].startswith("ready") and "saves not made" in readiness.check()[1]
        await link.call("put", "d", b"state d")
        return took, hung, asked, await link.call("take", "d")

    readiness = Readiness()
    readiness.store = link
    try:
        took, hung, asked, state = asyncio.run(scenario())
    finally:
        store.running.set()
        link.close()
    assert took >= 0.3 and hung == 1 and asked == 0 and state == b"state d"
    calls = link.counts()[0]
    assert calls["put", "timeout"] == 1 and calls["put", "down"] >= 1 and calls["put", "ok"] == 2
    assert link.outages == 1


def test_a_full_queue_refuses_at_once_and_a_call_queued_past_its_deadline_is_dropped_unrun():
    store = HangingStore()
    link = StoreLink(store, max_queue=2, ping_every_s=10.0)

    async def scenario():
        store.running.clear()
        first = asyncio.create_task(link.call("put", "a", b"a", deadline_s=0.4))  # runs, hangs
        await asyncio.sleep(0.05)
        second = asyncio.create_task(link.call("put", "b", b"b", deadline_s=0.2))  # waits behind it
        third = asyncio.create_task(link.call("put", "c", b"c", deadline_s=0.2))
        await asyncio.sleep(0.05)
        with pytest.raises(StoreBusy, match="queue is full"):
            await link.call("put", "d", b"d")
        busy = not first.done() and store.answered == 0  # refused while the first call still hangs
        results = await asyncio.gather(first, second, third, return_exceptions=True)
        store.running.set()
        await asyncio.sleep(0.3)  # (the thread reaches the queued ones)
        return busy, results

    try:
        busy, results = asyncio.run(scenario())
    finally:
        store.running.set()
        link.close()
    assert busy and all(isinstance(r, StoreTimeout) for r in results)
    calls = link.counts()[0]
    assert calls["put", "busy"] == 1 and calls["put", "dropped"] == 2  # never run: "b" and "c" are not stored
    assert store.take("b") is None and store.take("c") is None


def test_the_metrics_report_the_store_and_readiness_says_degraded_with_200():
    from streamer.health import answer

    store = HangingStore()
    link = StoreLink(store, ping_every_s=0.05)
    metrics = ServerMetrics()
    metrics.store = metrics.readiness.store = link
    try:
        store.running.clear()
        for _ in range(100):
            if not link.up:
                break
            time.sleep(0.05)
        text = metrics.exposition()[0].decode()
        got = answer("GET", "/readyz", metrics.readiness)
    finally:
        store.running.set()
        link.close()
    assert "dimgestor_store_up 0.0" in text and "dimgestor_degraded 1.0" in text and "dimgestor_ready 1.0" in text
    assert "dimgestor_store_outages_total 1.0" in text
    assert got.status == 200 and got.body.startswith(b"degraded: state store unreachable")


def test_a_store_call_that_never_returns_marks_the_store_down_all_the_same(monkeypatch):
    """A client without timeouts: the link's thread is held, yet the worker sees the store down (and says so)."""
    from streamer import store_link

    monkeypatch.setattr(store_link, "STUCK_S", 0.3)
    store = HangingStore(hang_s=30.0)
    store.running.clear()
    link = StoreLink(store, ping_every_s=0.05)  # (its first ping hangs)
    try:
        for _ in range(100):
            if not link.up:
                break
            time.sleep(0.05)
        why = link.health()
    finally:
        store.running.set()
        link.close()
    assert why is not None and "has not returned for" in why, why


def test_a_healthy_stores_no_reaches_the_caller_as_it_is_and_is_no_outage():
    """A spent token, a live session, a state too large: the store answered (`StoreAnswer`), so the caller gets
    that answer (a resume told `session_live`, a save counted too large) and the store stays up."""
    from streamer.handover import SessionLive, StateRefused

    store = MemoryStore(max_bytes=100)
    link = StoreLink(store, ping_every_s=0.1)

    async def scenario():
        await link.call("put", "a", b"state a", True)  # (live: its connection holds it)
        with pytest.raises(SessionLive):
            await link.call("take", "a")
        with pytest.raises(StateRefused, match="cap"):
            await link.call("put", "b", b"x" * 101)
        await link.call("release", "a")
        assert await link.call("take", "a") == b"state a"
        with pytest.raises(StateRefused) as spent:
            await link.call("put", "a", b"state a again")
        return spent.value.reason

    try:
        assert asyncio.run(scenario()) == "spent"
        assert link.up and link.outages == 0
        counts, _ = link.counts()
        assert counts[("take", "refused")] == 1 and counts[("put", "refused")] == 2, counts
    finally:
        link.close()
