"""The gain tuner: differentiable machine objectives minimised with optax, and validated gain files.

* :mod:`tune.config`: :class:`~tune.config.TuneConfig`, the job's settings (embedded defaults, YAML);
* :mod:`tune.space`: parameter groups, log parametrisation, box bounds;
* :mod:`tune.run`: the objective over scenarios and :func:`~tune.run.optimise` (checkpoints, resume);
* :mod:`tune.export`: the ``pusupu-gains`` YAML schema (write, load, validate) and ros2_control PID export;
* :mod:`tune.job`: ``pusupu tune``, from configuration to gain file, report and plots.
"""
