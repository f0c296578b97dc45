"""Evaluation: trajectory, map and object metrics, and the Results container."""
