"""The serving engine's names in one import: sessions (`streamer.sessions`), the schedulers their inference
runs on (`streamer.scheduling`) and the frames they make (`streamer.frames`). Each concept lives in its own
module; this one only gathers them for callers that want the engine as a whole (`streamer.server`)."""

from streamer.frames import Frame
from streamer.scheduling import BatchStats, PoolScheduler, RankedExecutor, Scheduler, StreamBatcher, WindowPolicy
from streamer.sessions import AudioClock, Session, Stats

__all__ = ["Frame", "Session", "Stats", "AudioClock", "Scheduler", "StreamBatcher", "RankedExecutor",
           "PoolScheduler", "BatchStats", "WindowPolicy"]
