"""Hardware bridge: runs the loop step functions of :mod:`pusupu_jax.loops` against real drives.

Installed as its own package beside :mod:`pusupu_jax`; it has no public API yet.
"""
