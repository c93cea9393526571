"""Exact finite-dimensional filters of the seeds."""
