"""The speech front ends: 16 kHz samples -> 100 Hz feature frames, incrementally, with state as a value. The
contract and the log-mel front end (`base`), the speech front end that hears speech rather than a speaker
(`speech`), it plus a pretrained speech embedding (`embed`), and the mel filterbank they share (`mel`)."""

from dimgestor.frontend.base import AudioFrontEnd, FrontEndState, LogMelFrontEnd, PretrainedFrontEnd, build_frontend

__all__ = ["AudioFrontEnd", "LogMelFrontEnd", "PretrainedFrontEnd", "FrontEndState", "build_frontend"]
