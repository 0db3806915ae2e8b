"""The gain tuner: differentiable machine objectives minimised with optax, and validated gain files.

* :mod:`pusupu_jax.tune.config`: :class:`~pusupu_jax.tune.config.TuneConfig`, the job's settings (embedded defaults,
  YAML);
* :mod:`pusupu_jax.tune.space`: parameter groups, log parametrisation, box bounds;
* :mod:`pusupu_jax.tune.run`: the objective over scenarios and :func:`~pusupu_jax.tune.run.optimise` (checkpoints,
  resume);
* :mod:`tune.export`: the ``pusupu-gains`` YAML schema (write, load, validate) and ros2_control PID export;
* :mod:`pusupu_jax.tune.job`: ``pusupu tune``, from configuration to gain file, report and plots.
"""
