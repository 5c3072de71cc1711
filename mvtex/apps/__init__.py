"""Whole-pipeline applications: the benchmark, the demo and its report.
"""
