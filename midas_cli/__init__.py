"""midas: record and analyse multimodal data in robot-assisted surgery (the MiDAS system)."""

__version__ = "0.1.0"
