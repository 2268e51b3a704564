"""Layer ``guidance``: CLIP loading (real weights, a local checkpoint, or the tiny random test
model; fails fast offline), the torchvision compatibility shim, and the optimisation objective
(CLIP similarity, or image targets)."""
