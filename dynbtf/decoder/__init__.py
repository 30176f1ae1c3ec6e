"""Decoder kernels: the fast ways to run a representation's MLP decoder.

* :mod:`~dynbtf.decoder.fused_mlp` -- the training-time fused MLP (forward and backward in one
  native call, :mod:`~dynbtf.decoder.native`, with a torch fallback);
* :mod:`~dynbtf.decoder.fast_decode` -- the evaluation-time numba kernel for layer 1's angular part
  (angular planes pre-multiplied by layer 1's weights) and direction checks;
* :mod:`~dynbtf.decoder.native` -- the C++ kernel, compiled on first use.

The synthesis kernels stay with their methods (``dynbtf/synthesis/<method>/kernel.py``, on the building blocks of
:mod:`dynbtf.synthesis.kernels`): they share the synthesis lattice and hash, and moving them here would make the
two packages import each other.
"""
