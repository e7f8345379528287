"""uavloc: UAV-aided 5G NR user localization (shared project-wide pieces)."""

__version__ = "0.1.0"
