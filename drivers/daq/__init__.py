"""A galvo on an NI-DAQ card through the ``nidaqmx`` package: ``transport`` (the package, tasks,
errors), ``protocol`` (raster -> samples and marker lines, calibration; no I/O), ``device``
(``DaqGalvo``, the scan interface of our serial galvo: raster on the card's sample clock,
count-gated stepped by the host on the session's counts)."""

from .device import DaqGalvo
from .protocol import DaqCalibration, MarkerLine, raster_waveform
from .transport import DaqError, DaqLibraryMissingError, DaqTransport, list_devices

__all__ = ["DaqGalvo", "DaqCalibration", "MarkerLine", "raster_waveform", "DaqTransport",
           "DaqError", "DaqLibraryMissingError", "list_devices"]
