"""Numeric kernels the pipeline's stages share: compiling loops to machine code (``jit``), linear
algebra on small matrices (``linalg``) and the standard normal distribution (``normal``)."""
