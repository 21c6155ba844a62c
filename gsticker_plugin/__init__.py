"""gsticker: GeometrySticker ownership messages for Nerfstudio radiance fields."""

__version__ = "0.1.0"
