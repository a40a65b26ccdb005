"""TCSPC time tagger over USB: transport (pyusb), protocol (control payloads, T3 records), device
(``Tagger``) and the reader thread. The wire protocol is in ``docs/protocols.md``."""

from spdepth.drivers.lazy import lazy_attributes

_LAZY = {"DEFAULT_URL": "device", "Tagger": "device", "TaggerSettings": "device",
         **{name: "protocol" for name in ("Binning", "Gap", "MarkerConfig", "StatusFlag", "TaggerIdentity",
                                          "TaggerStatus")},
         "TaggerReader": "reader", "lost_event": "reader",
         **{name: "t3" for name in ("T3DecoderState", "T3EncoderState", "decode_t3", "encode_t3")},
         "DeviceGoneError": "transport", "EndpointStallError": "transport", "UsbTransport": "transport"}
"""Loaded on first use: reading a file needs ``t3`` alone (``acq.ptu``, ``acq.readers.picoquant``),
not the device, its reader thread and pyusb (12 ms of every ``spdepth recon``'s start, on the
GIL while the kernels load)."""

__getattr__ = lazy_attributes(__name__, _LAZY)

__all__ = [
    "DEFAULT_URL", "Tagger", "TaggerSettings", "TaggerReader", "lost_event", "UsbTransport",
    "DeviceGoneError", "EndpointStallError", "T3DecoderState", "T3EncoderState", "decode_t3",
    "encode_t3", "Binning", "Gap", "MarkerConfig", "StatusFlag", "TaggerIdentity", "TaggerStatus",
]
