"""Physically based rendering in Mitsuba 3: the ``dynbtf`` BSDF plugin (the synthesized BTF's query at every shading
point, footprints, importance sampling) and scene rendering. Needs the ``render`` extra (``mitsuba``, ``drjit``)."""
