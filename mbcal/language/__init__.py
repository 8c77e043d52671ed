"""The model description language: text → syntax tree → checked :class:`Model`.

Modules, in the order the text flows through them (each imports only modules further down; the
import-linter contract in ``pyproject.toml`` keeps it so):

* ``load`` ties it together; ``urdf`` turns a URDF robot into model text;
* ``check`` runs the checker's passes: ``expand`` (templates, includes, names and ``scope``\\ s)
  and ``declarations`` (with ``shapes``, ``sensors`` and ``targets``), whose expressions
  ``expressions`` compiles;
* ``ir`` and ``soa`` evaluate expression graphs (``graph``) with arrays and in
  structure-of-arrays form (``soa_math``); ``functions`` is the catalogue of the language's
  functions that the checker and both evaluators share; ``arguments`` matches calls to
  signatures;
* ``model`` is the checked model (``summary`` prints it), ``meshes`` reads mesh files, and
  ``parse`` turns text into the syntax tree of ``ast`` (through the cache folder; ``syntax``
  is the Lark parser it falls back on).

This file only re-exports.
"""

from mbcal.language.load import load_model, load_model_text, load_urdf
from mbcal.language.model import Model

__all__ = ["load_model", "load_model_text", "load_urdf", "Model"]
