"""Retargeting: our motion onto a user's rig (BVH, glTF/GLB, VRM) whatever its rest pose, names and proportions."""

from dimgestor.retarget.rig import Rig, RigError, load_rig
from dimgestor.retarget.transfer import Retarget, Target, load_target, resolve_map

__all__ = ["Rig", "RigError", "load_rig", "Retarget", "Target", "load_target", "resolve_map"]
