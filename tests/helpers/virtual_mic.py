"""A real virtual microphone for tests: a private PulseAudio daemon whose null sinks' monitors PortAudio
captures through ALSA's `pulse` plugin. What `play()` plays into a sink, in real time, is what the
"microphone" hears. No sound hardware, no dbus, no system daemon: everything lives in one temp folder
and the daemon is stopped by its own pid.

ALSA devices it defines (PortAudio lists them by these names):
  pulse       the default source: the 48 kHz sink `mic48`'s monitor
  vmic44      the 44.1 kHz sink `mic44`'s monitor
  vmic_quiet  the monitor of a sink nothing ever plays into (a muted microphone)
  vspeaker    playback into `mic48` only: a device without input channels
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

DEFAULT_PA = """\
load-module module-null-sink sink_name=mic48 rate=48000 channels=1 sink_properties=device.description=dimgestor-48k
load-module module-null-sink sink_name=mic44 rate=44100 channels=1 sink_properties=device.description=dimgestor-44k
load-module module-null-sink sink_name=quiet rate=48000 channels=1 sink_properties=device.description=dimgestor-quiet
load-module module-native-protocol-unix auth-anonymous=1
set-default-sink mic48
set-default-source mic48.monitor
"""
DAEMON_CONF = """\
exit-idle-time = -1
enable-shm = no
flat-volumes = no
"""
ASOUNDRC = """\
pcm.vmic44 {
  type pulse
  device "mic44.monitor"
  hint { show on; description "dimgestor virtual microphone, 44.1 kHz" }
}
pcm.vmic_quiet {
  type pulse
  device "quiet.monitor"
  hint { show on; description "dimgestor virtual microphone that hears nothing" }
}
pcm.vspeaker {
  type asym
  playback.pcm { type pulse; device "mic48" }
  hint { show on; description "dimgestor virtual speaker (playback only)" }
}
"""


def missing() -> str | None:
    """Why a virtual microphone cannot be made here, or None."""
    for tool, package in [("pulseaudio", "pulseaudio"), ("paplay", "pulseaudio-utils"), ("pactl", "pulseaudio-utils")]:
        if shutil.which(tool) is None:
            return f"`{tool}` not found (apt install {package})"
    if not glob.glob("/usr/lib/*/alsa-lib/libasound_module_pcm_pulse.so") + glob.glob("/usr/lib*/alsa-lib/libasound_module_pcm_pulse.so"):
        return "ALSA's pulse plugin not found (apt install libasound2-plugins)"
    try:
        import sounddevice  # noqa: F401
    except OSError as e:
        return f"PortAudio not found ({e}; apt install libportaudio2)"
    return None


@dataclass
class VirtualMic:
    folder: Path
    env: dict[str, str]  # for every process that captures from or plays into it
    daemon: subprocess.Popen
    players: list[subprocess.Popen] = field(default_factory=list)

    def play(self, wav: Path, sink: str = "mic48") -> subprocess.Popen:
        """Start playing `wav` into `sink` in real time (paplay); returns at once."""
        p = subprocess.Popen(["paplay", f"--device={sink}", str(wav)], env=self.env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.players.append(p)
        return p

    def stop_players(self) -> None:
        for p in self.players:
            if p.poll() is None:
                p.terminate()
                p.wait(5)
        self.players.clear()

    def log(self) -> str:
        return (self.folder / "pulseaudio.log").read_text(errors="replace")[-3000:]


@contextmanager
def virtual_mic(folder: Path):
    """A running private PulseAudio daemon with the devices above; skips the test where it cannot be made."""
    if why := missing():
        pytest.skip(f"no virtual microphone: {why}")
    runtime, config = folder / "run", folder / "config"
    (config / "alsa").mkdir(parents=True)
    runtime.mkdir(mode=0o700)
    (folder / "default.pa").write_text(DEFAULT_PA)
    (folder / "daemon.conf").write_text(DAEMON_CONF)
    (config / "alsa" / "asoundrc").write_text(ASOUNDRC)  # alsa-lib reads $XDG_CONFIG_HOME/alsa/asoundrc
    env = {**os.environ, "XDG_RUNTIME_DIR": str(runtime), "PULSE_RUNTIME_PATH": str(runtime / "pulse"),
           "PULSE_SERVER": f"unix:{runtime / 'pulse' / 'native'}", "PULSE_STATE_PATH": str(folder / "state"),
           "XDG_CONFIG_HOME": str(config), "HOME": str(folder)}
    for name in ("PULSE_SINK", "PULSE_SOURCE", "ALSA_CONFIG_PATH"):  # the caller's settings must not leak in
        env.pop(name, None)
    # -n: no system default.pa (it wants udev/dbus); root is allowed in user mode with a warning
    cmd = ["pulseaudio", "-n", "--daemonize=no", "--exit-idle-time=-1", "--use-pid-file=no", "--disallow-exit=no",
           "--log-target=stderr", f"--file={folder / 'default.pa'}", "--disable-shm=yes"]
    with open(folder / "pulseaudio.log", "w") as log:
        daemon = subprocess.Popen(cmd, env={**env, "PULSE_CONFIG": str(folder / "daemon.conf")},
                                  stdout=log, stderr=subprocess.STDOUT)
    mic = VirtualMic(folder, env, daemon)
    try:
        deadline = time.monotonic() + 30
        while subprocess.run(["pactl", "info"], env=env, capture_output=True).returncode != 0:
            if daemon.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"PulseAudio did not start (exit {daemon.poll()}):\n{mic.log()}")
            time.sleep(0.1)
        yield mic
    finally:
        mic.stop_players()
        if daemon.poll() is None:
            daemon.terminate()
            try:
                daemon.wait(10)
            except subprocess.TimeoutExpired:
                daemon.kill()
                daemon.wait()


def speech_then_silence(path: Path, speech_s: float, silence_s: float) -> Path:
    """A 16 kHz WAV: the first `speech_s` of the bundled espeak-ng clip, then digital silence."""
    from dimgestor.audio import load_wav, save_wav
    from streamer.sources import DEMO_WAV

    speech = load_wav(DEMO_WAV)[: int(speech_s * 16000)]
    save_wav(path, np.concatenate([speech, np.zeros(int(silence_s * 16000), np.float32)]), 16000)
    return path
