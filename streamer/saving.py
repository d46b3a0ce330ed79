"""One connection's calls to the state store (streamer/handover.py): its periodic saves, the hand-over's save,
resume's take, and the forget and release calls, each on the store's own thread within its deadline
(`streamer.store_link.StoreLink`, through the server's `store_call`), the puts counted (streamer/metrics.py).

The connection (`streamer.connection.Client`) makes the states and tells its session machine what came of them;
this holds what is under way in the store, so that a session's `end` can wait for a save that is."""

from __future__ import annotations

import asyncio
import logging
from typing import Awaitable, Callable, Iterable

from dimgestor.audio import SAMPLE_RATE
from streamer import client_session as S
from streamer.log_limit import ErrorLog
from streamer.metrics import ServerMetrics
from streamer.sources import PushSource, make_resampler


class StoreCalls:
    """`store_call(name, *args)`: the store's method on its own thread within a deadline (raises
    `streamer.store_link.StoreError`); `departures`: the server's rate-limited log of what a client lost."""

    def __init__(self, store_call: Callable[..., Awaitable], metrics: ServerMetrics, departures: ErrorLog, who: str):
        self.store_call, self.metrics, self.departures, self.who = store_call, metrics, departures, who
        self.under_way: set[asyncio.Task] = set()  # every call not finished (periodic saves, forget, release)
        self.periodic: set[asyncio.Task] = set()  # the periodic saves not finished (a session's `end` waits)

    async def put(self, token: str, data: bytes, live: bool) -> None:
        """A state to the store, counted; raises what the store raises (StateRefused: counted by its reason)."""
        from streamer.handover import StateRefused

        try:
            await self.store_call("put", token, data, live)
        except StateRefused as e:
            self.metrics.state_puts_refused.labels(e.reason).inc()
            raise
        self.metrics.states_put.inc()
        self.metrics.state_bytes_put.inc(len(data))

    def save_periodic(self, token: str, data: bytes, saved: Callable[[], None]) -> None:
        """--save-state-every: `data` under the session's standing token (overwritten each time); `saved()` once
        the store has it. A store that is down or refuses it: the session goes on unsaved, said (rate-limited)."""

        async def store() -> None:
            try:
                await self.put(token, data, live=True)
            except Exception as e:
                self.departures(logging.WARNING, f"periodic save of {self.who}'s session failed "
                                                 f"({type(e).__name__}: {e})")
                return
            saved()

        self._track(asyncio.get_running_loop().create_task(store()), self.under_way, self.periodic)

    async def periodic_done(self) -> None:
        """Wait for the periodic saves under way (wait, not gather: a client that leaves cancels the waiter, never
        the saves)."""
        if self.periodic:
            await asyncio.wait(set(self.periodic))

    async def take(self, token: str) -> S.Taken:
        """resume_session: the state saved under `token`, taken from the store, as the machine's `Taken`."""
        from streamer.handover import SessionLive

        try:
            return S.Taken(await self.store_call("take", token))
        except SessionLive as e:
            return S.Taken(None, live_s=e.retry_after_s)
        except Exception as e:
            return S.Taken(None, f"{type(e).__name__}: {e}")

    def later(self, name: str, token: str) -> None:
        """forget (an ended session's periodic save: nobody will resume it) or release (the connection is gone:
        its last save may be resumed now), not waited for; a store that is down drops them by their TTLs."""

        async def call() -> None:
            try:
                await self.store_call(name, token)
            except Exception:
                pass

        self._track(asyncio.get_running_loop().create_task(call()), self.under_way)

    @staticmethod
    def _track(task: asyncio.Task, *sets: set) -> None:
        for tasks in sets:
            tasks.add(task)
            task.add_done_callback(tasks.discard)


STORE_DRAIN_DEADLINE_S = 2.0  # a hand-over's save: a store that takes longer is taken as unreachable


class ServerStore:
    """A worker's side of its state store: every call on the store's own thread within its deadline (`StoreLink`;
    while draining, within the hand-over's bound too), the leases of the sessions live here renewed, and the
    hand-over of its sessions when it stops."""

    def __init__(self, store, departures: ErrorLog):
        from streamer.store_link import StoreLink

        self.link = StoreLink(store)  # its calls, off the real-time path
        self.departures = departures
        self.drain_until: float | None = None  # (loop time) while draining: the puts' deadline
        self.unsaved: dict = {}  # while draining: the clients whose sessions the store could not take, and why

    async def call(self, name: str, *args):
        """The store's method `name` (raises `streamer.store_link.StoreError`)."""
        deadline_s = None
        if self.drain_until is not None:
            deadline_s = max(0.0, min(self.drain_until - asyncio.get_running_loop().time(), STORE_DRAIN_DEADLINE_S))
        return await self.link.call(name, *args, deadline_s=deadline_s)

    async def keep_leases(self, clients: Callable[[], Iterable]) -> None:
        """Renews the leases of the sessions live here (`clients()`: the connections now), all in one store call
        every TOUCH_EVERY_S: their periodic-save tokens resume nothing while their connections last
        (streamer/handover.py)."""
        from streamer.handover import TOUCH_EVERY_S

        while True:
            await asyncio.sleep(TOUCH_EVERY_S)
            tokens = [c.machine.save_token for c in list(clients()) if c.machine.save_token is not None]
            if not tokens:
                continue
            try:
                await self.call("touch", tokens)
            except Exception as e:  # the store is down: the leases run out, the sessions go on
                self.departures(logging.WARNING, f"state store: leases of {len(tokens)} sessions not renewed "
                                                 f"({type(e).__name__}: {e})")

    async def hand_over(self, own: dict, deadline: float) -> set:
        """`own`: {client: its session's task}. Each session finishes the audio it holds (until `deadline`), then
        its state goes to the store and the client gets `goaway` with the token (streamer/handover.py). Returns
        the clients handed over; the others (not done in time, a store that failed or did not answer by
        `deadline`) get a `goaway` without a token from the server's `close` (`protocol.goaway_unsaved`, with why
        from `unsaved`): they reconnect and start a fresh stream."""
        from streamer.handover import new_token

        loop = asyncio.get_running_loop()
        # all of them before any await: audio that arrives meanwhile is ignored, never refused
        sources = [c.hand_over() for c in own if c.session is not None]  # (None: left meanwhile)
        for source in sources:
            if source is not None:
                await source.close()
        done, _ = await asyncio.wait(own.values(), timeout=max(0.0, deadline - loop.time()))
        ready = [c for c, task in own.items()
                 if task in done and not task.cancelled() and task.exception() is None and c.session is not None]
        # (not finished in time, failed, or its client left: not saved) all saved at once, each within `deadline`
        saved = await asyncio.gather(*(c.save_handed_over(new_token()) for c in ready))
        for c, ok in zip(ready, saved):
            if not ok:
                why = f"is unreachable: {self.link.down_reason}" if not self.link.up else "failed or was busy"
                self.unsaved[c] = f"could not save the session (the state store {why})"
        return {c for c, ok in zip(ready, saved) if ok}


class ConnectionSaves:
    """`streamer.connection.Client`'s periodic saves, hand-over and resume: its session's state made and given to
    the store (`StoreCalls`, its `store`), or taken from it and restored, and its machine told how it went."""

    async def _take_state(self, token: str) -> list:
        """resume_session: the saved state under `token`, taken from the store; the machine hears how it went."""
        return await self.apply(self.machine.handle(await self.store.take(token)))

    def hand_over(self) -> PushSource | None:
        """The server stops with a state store: the session stops after the audio it holds, unfinished (its
        resampler is saved, not flushed); returns its audio queue, for the caller to close."""
        for a in self.act(self.machine.handle(S.HandOver())):
            if isinstance(a, S.EndAudio):
                self.session.handover = True
                source, self.source = self.source, None
                return source
        return None

    async def save_handed_over(self, token: str) -> bool:
        """Its session, stopped by `hand_over`, to the store under `token`, and `goaway` to the client; False
        if the store failed (the session then ends as without one)."""
        session, state, m = self.session, self.session.stream.state, self.machine
        frames, rate, encoding = m.frames, m.audio.rate, m.encoding

        def save():
            # (in the prep thread, after any resampling under way there) Audio at another rate than 16 kHz goes
            # on exactly when the resampler is saved too, and every output it gave reached the stream: the
            # client then re-sends from the resampler's own input count.
            samples, extra, r = state.samples_in * rate // SAMPLE_RATE, {}, self.resampler
            if r is not None and r.outputs == state.samples_in:
                extra["resampler"], samples = r.get_state(), r.inputs
            return session.snapshot(frames, state, rate=rate, encoding=encoding, **extra), samples

        loop = asyncio.get_running_loop()
        try:
            data, samples = await loop.run_in_executor(self.svc.prep, save)
            await self.store.put(token, data, live=False)  # (a fresh token: no lease, resumable at once)
        except Exception as e:  # the store is down, or refused it (too large)
            self.svc.departures(logging.WARNING, f"session of {self.who} not saved ({type(e).__name__}: {e}): ended")
            return False
        self.act(m.handle(S.HandedOver(token, samples)))
        return True

    async def _restore(self, data: bytes) -> None:
        """resume_session: the taken state becomes the new session's (`Session.restore`)."""
        from dimgestor.streaming.savestate import StateError

        session, rate = self.session, self.machine.audio.rate
        try:
            meta = await asyncio.get_running_loop().run_in_executor(self.svc.prep, session.restore, data)
        except StateError as e:  # refused, with the reason: the client goes on with a fresh session
            await self.apply(self.machine.handle(S.NotRestored(str(e))))
            return
        except Exception as e:  # a bug (restore raises StateError only): said here, and no resume either
            self.errors(logging.ERROR, f"restoring a saved state failed: {type(e).__name__}: {e}", exc_info=True)
            await self.apply(self.machine.handle(S.NotRestored(f"the saved state could not be restored "
                                                               f"({type(e).__name__})")))
            return
        inputs = None
        if meta.get("resampler") is not None and int(meta.get("rate", 0)) == rate:  # its rate converter goes on too
            self.resampler = make_resampler(rate)
            self.resampler.set_state(meta["resampler"])
            inputs = self.resampler.inputs
        self.act(self.machine.handle(S.Restored(int(meta["frames"]), session.stream.state.samples_in,
                                                           inputs)))

    def _save(self, save: S.SaveState) -> None:
        """--save-state-every, between two windows: the state, copied now (a few ms for a megabyte: the next
        window moves it on), goes to the store under the session's standing token (overwritten each time)."""
        m = self.machine
        data = self.session.snapshot(save.frames, rate=m.audio.rate, encoding=m.encoding)
        self.store.save_periodic(save.token, data, lambda: self.act(
            m.handle(S.Saved(save.session_id, save.token, save.samples, save.frames))))
