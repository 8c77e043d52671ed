"""Geometry in JAX: rigid transforms, camera projection, the shape registry and ray casting.

Nothing here knows the model language: these are the kernels the modeler, the measurement
models, the renderer and the URDF importer share.
"""
