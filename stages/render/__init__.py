"""Closed-form spherical-Gaussian rendering: pure functions on tensors (no state, no devices)."""
