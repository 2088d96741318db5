"""Part labelers: which segments are static, which move together, and a joint-type prior."""
from .base import PartLabeler, labels_from_segment_maps
from .mock import MockLabeler
from .rules import RuleBasedLabeler

__all__ = ["MockLabeler", "PartLabeler", "RuleBasedLabeler", "VlmLabeler", "labels_from_segment_maps"]


def __getattr__(name: str):
    """``VlmLabeler`` (optional, off by default) is imported on first use: it pulls in OpenCV."""
    if name == "VlmLabeler":
        from .vlm import VlmLabeler

        return VlmLabeler
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
