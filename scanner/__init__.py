"""slscan scanner core: devices, patterns, acquisition, sessions, decoding, reconstruction."""

__version__ = "0.1.0"
