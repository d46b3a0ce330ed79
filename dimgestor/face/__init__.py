"""The speaking face: mouth shapes, blinks and brows from the same live audio as the body (`FaceStream`)."""

from dimgestor.face.names import DEFAULT_NAMES, NAME_SETS, check_name_set, convert, names_of
from dimgestor.face.stream import FaceOptions, FaceStream
from dimgestor.face.visemes import FACE_LABELS

__all__ = ["FaceStream", "FaceOptions", "FACE_LABELS", "NAME_SETS", "DEFAULT_NAMES", "convert", "names_of",
           "check_name_set"]
