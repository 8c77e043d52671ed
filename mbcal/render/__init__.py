"""Pictures: headless rendering of model views (pyrender), overlays on photos, residual plots.

Optional at import time: pyrender and matplotlib are loaded when a picture is made.
"""
