"""Benchmarks: modules that print figures, never part of the test run. Each runs from the
repository root with the project's environment as ``python -m benchmarks.<topic>.<name>`` (``--help``
says what it takes); the figures they printed, with dates and machines, are under
docs/measurements/, and docs/development/benchmarks.md lists them all.

Topics: ``render`` (the renderer's arithmetic and Mitsuba's), ``training`` (the optimisation step
and job: time, floors, levers, CPU and GPU), ``quality`` (recovery on Mitsuba's ground truth,
relighting and robustness), ``geometry`` (ray caches, the up axis), ``assets`` (bake, export,
levels of detail), ``workflow`` (whole runs, the plan, the report, the file gate). What they share
(meshes, fixtures, timing, the machine's rates and the FLOPs of a step) is :mod:`benchmarks.common`;
a benchmark imports ``stages`` and ``benchmarks.common``, never another benchmark, and ``stages``
never imports ``benchmarks``.
"""
