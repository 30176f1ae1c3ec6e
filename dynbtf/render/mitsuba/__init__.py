"""Physically based rendering in Mitsuba 3: the ``dynbtf`` BSDF plugin (Dr.Jit kernels of the synthesized BTF,
footprints, importance sampling) and scene rendering. Needs the ``render`` extra (``mitsuba``, ``drjit``)."""
