"""TANGO stylization workflow: the importable stages behind the Snakemake rules.

Nothing runs at import time: no model loads, no device queries, no global state.
"""

__version__ = "0.1.0"
