"""Throughput benchmarks (``python -m anm_torchrl.benchmarks.env``)."""
