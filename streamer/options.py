"""`dimgestor serve`'s options: one typed, frozen value, validated once, with one default per option.

The command line is built from these fields (`streamer.cli` takes each flag's default from here and maps
the parsed flags back by field name; a flag is named like its field but for those in FLAGS), and a test or an
embedding program builds the same value directly.
What is checked here needs nothing but the values (and, for --record, that its folder exists): opening
the source, the model and the sinks is `streamer.server.build`'s job.
"""

from __future__ import annotations

import re

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from streamer.handover import DEFAULT_MAX_BYTES as DEFAULT_STATE_MAX_BYTES

MAX_SESSIONS = 32  # most WebSocket clients sending their own audio at once
PING_INTERVAL_S, PING_TIMEOUT_S = 20.0, 20.0  # the WebSocket keepalive


class ServeError(RuntimeError):
    """A configuration problem found before serving (bad option, checkpoint, map, record path...)."""


HostPort = tuple[str, int]
# The fields whose flag is not named after them (renamed flags: the fields kept their names for the code that reads
# them; `--osc` is still accepted, as a deprecated spelling; `--device` was the input device's until it became the
# compute device's)
FLAGS = {"osc": "--vmc", "device": "--input-device", "compute_device": "--device"}
COMPUTE_DEVICE = re.compile(r"cpu|cuda(:\d+)?")


def flag_of(field: str) -> str:
    """The command-line flag that sets a field: "window_ms" -> "--window-ms", "osc" -> "--vmc"."""
    return FLAGS.get(field, "--" + field.replace("_", "-"))


class ServeOptions(BaseModel):
    """Every `dimgestor serve` flag, by its field name (`--window-ms` is `window_ms`, `--vmc` is `osc`: FLAGS);
    `dimgestor serve --help` says what each one does."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # the server's own audio
    source: str = "demo"  # "mic", "demo", a WAV path, or "ws" (clients' own audio only)
    device: str | None = None  # --input-device, for --source mic: an input device index or part of its name
    rate: int | None = Field(None, gt=0)  # --source mic: capture rate (None: the device's own)
    gain: float = 0.0  # --source mic: dB
    gate: float | None = None  # --source mic: noise gate, dBFS
    fast: bool = False  # a file source as fast as inference allows, not in real time
    loop: bool = False  # a file source repeated forever
    # the model and its sampling
    checkpoint: str | None = None  # None: the embedded default model
    steps: int | None = Field(None, ge=1)  # None: the checkpoint's sample_steps
    seed: int = 0
    guidance: float | None = None  # None: the checkpoint's
    speaker: str | None = None  # a speaker of a model trained with a speaker condition; None: no speaker in particular
    root: Literal["tether", "free", "lock"] = "tether"
    tether_s: float = Field(5.0, gt=0)
    smooth: float | None = None  # One Euro cutoff in Hz, 0 = off; None: the checkpoint's setting
    window_ms: int = Field(200, ge=10, le=5000)
    no_batch: bool = False
    compute_device: str = "cpu"  # --device: where the model runs: cpu, cuda, cuda:N
    backend: Literal["torch", "onnxruntime"] = "torch"  # onnxruntime: the ONNX export (its batched graphs)
    onnx: str | None = None  # with backend onnxruntime: an export folder of the checkpoint (else exported at start)
    onnx_cache: str | None = None  # with backend onnxruntime and no --onnx: where exports are kept (None: per-user)
    # the WebSocket server (and the viewer on its port)
    ws: HostPort = ("127.0.0.1", 8765)
    no_ws: bool = False
    http: tuple[str | None, int] | None = None  # deprecated: a second address serving the same (None host: --ws's)
    max_sessions: int = Field(MAX_SESSIONS, ge=1, le=4096)
    faces_beyond_capacity: Literal["busy", "no-face"] = "busy"  # a face that would not keep real time: refused or left out
    token: str | None = None
    token_file: str | None = None
    allow_origin: tuple[str, ...] = ()
    no_client_audio: bool = False
    wait_client: bool = False
    ping_interval: float = Field(PING_INTERVAL_S, ge=0, le=3600)  # 0: no keepalive
    ping_timeout: float = Field(PING_TIMEOUT_S, gt=0, le=3600)
    no_metrics: bool = False  # /metrics not served (/healthz and /readyz always are)
    state_store: str | None = None  # "memory" or redis://...: sessions are handed over on SIGTERM (handover.py)
    state_ttl: float = Field(300.0, gt=0, le=86400)
    save_state_every: float | None = Field(None, gt=0, le=3600)  # s of audio between a session's periodic saves
    state_max_bytes: int = Field(DEFAULT_STATE_MAX_BYTES, gt=0)  # a larger state is not saved (counted)
    state_secret_file: str | None = None  # the workers' shared secret sealing saved states ($DIMGESTOR_STATE_SECRET)
    # VMC (OSC over UDP)
    osc: HostPort | None = None  # --vmc HOST:PORT
    vmc_positions: Literal["hips", "all"] = "hips"
    vmc_hips_height: float | None = None
    vmc_root: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    vmc_bones: Literal["all", "upper"] = "all"
    vmc_max_bytes: int = 0
    vmc_jitter_ms: float | None = Field(None, ge=0, le=5000)  # None: one window (window_ms)
    # the face
    face: Literal["vrm0", "vrm1", "arkit", "oculus", "none"] = "vrm0"  # the default name set; none: no face
    smile: float = Field(0.0, ge=0, le=1)
    # what hears the mouth: the face's network, pocketsphinx, or both (their mouths averaged)
    face_listener: Literal["net", "pocketsphinx", "net+pocketsphinx"] = "net"
    face_process: bool = False  # the faces made in a child process beside the inference thread
    # the rest
    record: str | None = None  # a BVH path (.glb, .vrma or .npz: that file too, from the BVH beside it)
    humanoid_map: str | None = None  # None: streamer/maps/zeggs.json
    target: str | None = None  # a rig (.bvh, .glb, .gltf, .vrm): frames for clients and VMC are on it
    target_map: str | None = None  # its bone map over the names recognised
    status_every: float = 2.0  # seconds; 0: no status lines
    max_seconds: float | None = None

    @classmethod
    def parse(cls, **values) -> "ServeOptions":
        """Validated options, or a ServeError naming the flag at fault."""
        try:
            return cls(**values)
        except ValidationError as e:
            raise ServeError(_message(e.errors()[0])) from None

    @property
    def device_id(self) -> int | str | None:
        """--input-device as PortAudio takes it: an index if it is one, else a part of the name."""
        return int(self.device) if self.device is not None and self.device.isdigit() else self.device

    @property
    def smoothing(self):
        """--smooth as `Session` takes it ("config", None = off, or a cutoff in Hz)."""
        from dimgestor.cli_help import smoothing_from_flag

        return smoothing_from_flag(self.smooth)

    def vmc(self):
        """The --vmc-* flags as `VmcOptions`."""
        from streamer.vmc import VmcOptions

        return VmcOptions(self.vmc_positions, self.vmc_hips_height, self.vmc_root, self.vmc_bones, self.vmc_max_bytes)

    @field_validator("allow_origin", mode="before")
    @classmethod
    def _origins(cls, value):
        from streamer.request_checks import allowed_origin

        value = tuple(value or ())
        bad = [o for o in value if allowed_origin(o) is None]
        if bad:
            raise ValueError(f"--allow-origin {bad[0]!r} is not an origin (scheme://host[:port], e.g. "
                             f"http://myapp.example:3000, or '*')")
        return value

    @field_validator("compute_device")
    @classmethod
    def _compute_device(cls, value):
        if not COMPUTE_DEVICE.fullmatch(value):  # (what --device meant on serve before: the microphone)
            raise ValueError(f"--device {value!r}: the device the model runs on (cpu, cuda or cuda:N); a microphone "
                             f"is --input-device (--input-device {value})")
        return value

    @field_validator("guidance")
    @classmethod
    def _guidance(cls, value):
        from dimgestor.model.diffusion import check_guidance

        if value is not None:
            try:
                check_guidance(value)
            except ValueError as e:
                raise ValueError(f"--guidance: {e}") from None
        return value

    @field_validator("smooth")
    @classmethod
    def _smooth(cls, value):
        if value is not None:
            from dimgestor.cli_help import smoothing_from_flag

            smoothing_from_flag(value)  # raises with the flag's own message
        return value

    @model_validator(mode="after")
    def _together(self) -> "ServeOptions":
        if self.no_ws and self.http is not None:
            raise ValueError("--http serves the viewer from the WebSocket server (drop --no-ws)")
        if self.no_ws and self.source == "ws":
            raise ValueError("--source ws needs the WebSocket server (drop --no-ws)")
        if self.record and self.source == "ws":
            raise ValueError("--record records the server's own source; --source ws has none")
        if self.record and not Path(self.record).resolve().parent.is_dir():
            raise ValueError(f"--record {self.record}: folder {Path(self.record).resolve().parent} does not exist")
        if self.target_map is not None and self.target is None:
            raise ValueError("--target-map needs --target (the rig it maps)")
        if self.humanoid_map is not None and self.target is not None:
            raise ValueError("--humanoid-map maps the model's skeleton; with --target, map the target (--target-map)")
        if self.onnx is not None and self.backend != "onnxruntime":
            raise ValueError("--onnx is an export for --backend onnxruntime: give that too")
        if self.onnx_cache is not None and (self.backend != "onnxruntime" or self.onnx is not None):
            raise ValueError("--onnx-cache is where --backend onnxruntime keeps the exports it makes: give that "
                             "backend, without --onnx (an export of your own)")
        if self.backend == "onnxruntime" and self.state_store is not None:
            raise ValueError("--state-store saves torch stream states: sessions on --backend onnxruntime are not "
                             "handed over yet (use --backend torch)")
        if self.save_state_every is not None and self.state_store is None:
            raise ValueError("--save-state-every saves sessions to the state store: give --state-store too")
        if self.state_secret_file is not None and self.state_store is None:
            raise ValueError("--state-secret-file seals the states of the state store: give --state-store too")
        if self.osc is not None:
            try:
                self.vmc()
            except ValueError as e:
                raise ValueError(f"--vmc: {e}") from None
        return self


def _message(error: dict) -> str:
    """One pydantic error as the flag's message: "--window-ms must be in 10..5000, got 5"."""
    if error["type"] == "value_error":  # (ours: the message names the flag already)
        return str(error["ctx"]["error"])
    name, given = str(error["loc"][0]) if error["loc"] else "", error.get("input")
    flag = flag_of(name)
    field = ServeOptions.model_fields.get(name)
    b = {k: getattr(m, k) for m in (field.metadata if field else ()) for k in ("ge", "gt", "le")
         if getattr(m, k, None) is not None}
    if error["type"] not in ("greater_than_equal", "greater_than", "less_than_equal"):
        return f"{flag}: {error['msg']}, got {given!r}"
    if "le" in b:
        span = f"{b['ge']}..{b['le']}" if "ge" in b else f"({b['gt']}, {b['le']}]"
        return f"{flag} must be in {span}, got {given}"
    return f"{flag} must be {'>=' if 'ge' in b else '>'} {b.get('ge', b.get('gt'))}, got {given}"
