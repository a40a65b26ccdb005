"""The Qt window: live maps, pixel inspector, controls. Talks only to ``acq``."""
