"""Rendering: the only package that imports Mitsuba, and only when a :class:`Renderer` is made.

``import mbcapture.render`` is cheap and Mitsuba-free; :func:`ensure_llvm` picks a libLLVM that
does not crash Dr.Jit (>= 16) before Mitsuba is first imported.
"""

from .build import Environment, Guide, Light, Material, SceneBuild, Shape
from .llvm import ensure_llvm
from .renderer import Renderer

__all__ = ["ensure_llvm", "Renderer", "SceneBuild", "Shape", "Guide", "Material", "Light", "Environment"]
