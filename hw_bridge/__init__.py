"""The hardware bridge: the simulator's own loop functions (:mod:`pusupu_jax.cascade`) at real-time rate against drives.

* :mod:`pusupu_jax.hw_bridge.loop` (:class:`~pusupu_jax.hw_bridge.loop.BridgeLoop`,
  :func:`~pusupu_jax.hw_bridge.loop.plan`): the ticks compiled for
  the CPU, drive modes (CSV, CST, hybrid), the takeover without a step;
* :mod:`pusupu_jax.hw_bridge.session` (:class:`~pusupu_jax.hw_bridge.session.Bridge`): CiA 402 bring-up, the run, the
  safe stop, the report;
* :mod:`pusupu_jax.hw_bridge.runner`, :mod:`pusupu_jax.hw_bridge.safety`, :mod:`pusupu_jax.hw_bridge.cia402`;
* transports: :mod:`pusupu_jax.hw_bridge.protocol` + :mod:`pusupu_jax.hw_bridge.udp` (UDP v1),
  :mod:`pusupu_jax.hw_bridge.canopen_link` (CANopen).

The simulated robot that answers the bridge in tests and demonstrations is a package of its own
(:mod:`pusupu_jax.sim_robot`), since it imports the mechanism (MuJoCo), which this package never does.

``pusupu bridge`` and ``pusupu sim-robot`` run them (``docs/bridge.md``).
"""
