"""Layer ``render``: closed-form spherical-Gaussian rendering as pure functions on tensors (SG
algebra, shading), colour encoding, environment maps and HDR file I/O, and the kernels of the
float32 linear layers above it (``products``: oneDNN's or ATen's). No state, no devices."""
