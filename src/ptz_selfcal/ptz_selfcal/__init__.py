"""ptz_selfcal: online self-calibration of rotating and zooming cameras."""

__version__ = "0.1.0"
