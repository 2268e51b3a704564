"""Layer ``testing``: what the tests and the benchmarks share, not part of any run (as
``numpy.testing`` is to numpy). ``recovery``: the image-target recovery protocol the tests hold
floors for and ``python -m benchmarks.quality.image_targets`` measures (it runs the stages, so it
sits above them); ``precision``: float64 as the judge of the renderer's float32 and bfloat16
arithmetic at the extremes, which ``python -m benchmarks.render.precision`` prints in full and
``tests/render/test_precision.py`` checks."""
