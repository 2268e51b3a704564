"""Whole runs and what surrounds them: the grid's scaling, the plan's estimate against a run,
seconds per rule, the HTML report at scale and the file gate's cost."""
