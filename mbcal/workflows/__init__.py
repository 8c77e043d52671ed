"""Complete tasks built on the library: camera calibration from target images (Zhang's
initialisation, OpenCV-compatible results), target detection, and the seed's demo."""
