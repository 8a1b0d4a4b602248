"""labcal: calibrate serial industrial robots from three-target tracker measurements."""

__version__ = "0.1.0"
