"""The optimisation step and job: time against the FLOP floor, the CPU and GPU levers, the
compilation, kernel launches, the allocator, shadows' cost and non-finite values."""
