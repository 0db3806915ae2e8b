"""The ``pusupu`` command line: subcommands over the core (``pusupu_jax``) and its applications."""
