"""Ray-cache throughput and shadow rays; the up-axis guess."""
