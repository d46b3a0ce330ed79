"""The model: the DiM-Gestor network (`network`: fuzzy feature extractor + AdaLN Mamba-2 denoiser), its Mamba-2
mixer (`mamba2`), the diffusion schedule and per-frame noise (`diffusion`), the K-step sampler every stream runs
(`sampler`), the condition path for one stream or a group (`conditioning`) and the Transformer baseline
(`baselines`)."""

from dimgestor.model.network import (AdaLNMamba2Block, DenoiserState, DiMGestor, ExtractorState, FinalLayer,
                                     FuzzyFeatureExtractor, GestureEncoder, TimestepEmbedder, modulate)

__all__ = ["DiMGestor", "AdaLNMamba2Block", "FuzzyFeatureExtractor", "FinalLayer", "GestureEncoder",
           "TimestepEmbedder", "ExtractorState", "DenoiserState", "modulate"]
