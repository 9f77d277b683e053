"""Benchmarks of the research scores (run each as ``python -m research.benchmarks.<name>`` from the repository root)."""
