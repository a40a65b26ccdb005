"""Swabian Time Taggers through the ``Swabian-TimeTagger`` package: ``protocol`` (tags -> our
events, settings; no I/O), ``device`` (``SwabianTagger``, the package injected as its transport;
``SwabianReader``)."""

from .device import SwabianLibraryMissingError, SwabianReader, SwabianTagger
from .protocol import SwabianSettings, TagType, tags_to_events

__all__ = ["SwabianTagger", "SwabianReader", "SwabianSettings", "SwabianLibraryMissingError",
           "TagType", "tags_to_events"]
