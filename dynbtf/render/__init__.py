"""Rendering the synthesized BTF: :mod:`~dynbtf.render.mitsuba` (the Mitsuba 3 plugin and scenes) and
:mod:`~dynbtf.render.preview` (a small torch/NumPy renderer of a plane, for previews and tests). The two
are independent of each other (import-linter contract in ``pyproject.toml``)."""
