"""Gain tuner (issue 4): differentiable objectives minimised with optax, gain YAML export.

Installed as its own package beside :mod:`pusupu_jax`; it has no public API yet.
"""
