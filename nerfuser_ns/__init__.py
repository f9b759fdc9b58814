"""nerfuser_ns: register separately trained nerfstudio NeRFs from their re-renderings and blend them (NeRFuser)."""

__version__ = "0.1.0"
