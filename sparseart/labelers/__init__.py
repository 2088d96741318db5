"""Part labelers: which segments are static, which move together, and a joint-type prior."""
from .base import PartLabeler, labels_from_segment_maps
from .mock import MockLabeler
from .rules import RuleBasedLabeler

__all__ = ["MockLabeler", "PartLabeler", "RuleBasedLabeler", "labels_from_segment_maps"]
