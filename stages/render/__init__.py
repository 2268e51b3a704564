"""Layer ``render``: closed-form spherical-Gaussian rendering as pure functions on tensors (SG
algebra, shading), colour encoding, environment maps and HDR file I/O. No state, no devices."""
