"""Range data in: point clouds and depth images, automatic calibration from scans, and the
environment model manager (docs/range.md)."""
