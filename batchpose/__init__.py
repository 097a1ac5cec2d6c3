"""batchpose: learning-free 6D pose of textured objects in recorded camera logs (GNC-Pose)."""

__version__ = "0.1.0"
