"""DiM-Gestor: co-speech gesture generation with AdaLN Mamba-2 diffusion, streamed exactly."""

__version__ = "0.1.0"
