"""TCSPC time tagger over USB: transport (pyusb), protocol (control payloads, T3 records), device
(``Tagger``) and the reader thread. The wire protocol is in ``docs/protocols.md``."""

from spdepth.drivers.tagger.device import DEFAULT_URL, Tagger, TaggerSettings
from spdepth.drivers.tagger.protocol import (Binning, Gap, MarkerConfig, StatusFlag, TaggerIdentity,
                                     TaggerStatus)
from spdepth.drivers.tagger.reader import TaggerReader, lost_event
from spdepth.drivers.tagger.t3 import T3DecoderState, T3EncoderState, decode_t3, encode_t3
from spdepth.drivers.tagger.transport import DeviceGoneError, EndpointStallError, UsbTransport

__all__ = [
    "DEFAULT_URL", "Tagger", "TaggerSettings", "TaggerReader", "lost_event", "UsbTransport",
    "DeviceGoneError", "EndpointStallError", "T3DecoderState", "T3EncoderState", "decode_t3",
    "encode_t3", "Binning", "Gap", "MarkerConfig", "StatusFlag", "TaggerIdentity", "TaggerStatus",
]
