"""The web export: textures, decoder weights, a GLSL ES 3.00 shader and a WebGL2 viewer
(:func:`~dynbtf.export.web.exporter.export_web`); the shader source is :mod:`~dynbtf.export.web.shader`,
the viewer's files are in ``assets/``."""
