"""Evaluation: gesture quality metrics (`metrics`: FGD, BeatAlign, jerk) and `dimgestor eval` (`eval`): a model's
motion against real capture, per number of sampling steps."""
