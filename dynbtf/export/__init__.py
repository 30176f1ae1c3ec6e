"""Exports of a synthesized BTF to other tools (:mod:`dynbtf.export.web`: a WebGL2 viewer and GLSL shader)."""
