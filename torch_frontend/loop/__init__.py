"""Loop closure, part 1: keyframe features (FAST + BRIEF), bag of binary words, place recognition.

VINS-Mono's ``pose_graph`` front half, batched: ``fast``/``brief``/``hamming`` describe keyframes,
``Vocabulary`` turns descriptors into bags of words (DBoW2), ``PlaceDatabase`` answers "have I been
here before?" with VINS's ``detectLoop`` rule.
"""

from .database import PlaceDatabase
from .features import (
    brief,
    default_brief_pattern,
    fast,
    gaussian_blur_u8,
    hamming,
    load_brief_pattern,
    make_brief_pattern,
)
from .vocabulary import BowVector, Vocabulary, bow_to_dense

__all__ = [
    "BowVector",
    "PlaceDatabase",
    "Vocabulary",
    "bow_to_dense",
    "brief",
    "default_brief_pattern",
    "fast",
    "gaussian_blur_u8",
    "hamming",
    "load_brief_pattern",
    "make_brief_pattern",
]
