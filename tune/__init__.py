"""The gain tuner: differentiable machine objectives minimised with optax, and validated gain files.

* :mod:`pusupu_jax.tune.config`: :class:`~pusupu_jax.tune.config.TuneConfig`, the job's settings (embedded defaults,
  YAML);
* :mod:`pusupu_jax.tune.space`: parameter groups, log parametrisation, box bounds;
* :mod:`pusupu_jax.tune.run`: the problem, its scenarios, windows and objective, and the shared compiled gradient;
* :mod:`pusupu_jax.tune.optimise`: the one engine of ``tune`` and ``batch`` (clipped Adam, one jitted step over a
  batch of members, projection, multi-start); a single problem is a batch of one;
* :mod:`pusupu_jax.tune.state`: the tuner's state; :mod:`pusupu_jax.tune.checkpoint`: checkpoints of it, written
  atomically, read back only when they fit the run;
* :mod:`pusupu_jax.tune.progress`: the progress lines;
* :mod:`pusupu_jax.tune.job`: ``pusupu tune``, from configuration to gain file, report and plots;
* :mod:`pusupu_jax.tune.jobfile`, :mod:`pusupu_jax.tune.batch`, :mod:`pusupu_jax.tune.batchjob`,
  :mod:`pusupu_jax.tune.cluster`: ``pusupu batch``.
"""
