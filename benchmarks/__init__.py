"""Speed and accuracy measurements.  ``python -m benchmarks`` runs them all; see the README."""
