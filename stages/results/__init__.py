"""Layer ``results``: reading a finished results tree for the report stages (cell ids, summary
rows, origin checks, speed/accuracy and its Pareto front, figures). Imports only ``core``."""
