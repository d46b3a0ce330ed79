"""The streaming core: audio in chunks -> motion frames, exactly as the whole recording would give them
(`stream`), many streams stepped at once (`batch`), and a stream's state as bytes another process resumes
(`savestate`, with what a stored state must satisfy in `savestate_checks`)."""

from dimgestor.streaming.stream import GestureStream, StreamState, generate_offline

__all__ = ["GestureStream", "StreamState", "generate_offline"]
