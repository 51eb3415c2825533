"""Benchmarks of the package (python -m benchmarks.<name>); results go to results/benchmarks/."""
