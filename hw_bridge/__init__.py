"""The hardware bridge: the simulator's own loop functions (:mod:`pusupu_jax.cascade`) at real-time rate against drives.

* :mod:`hw_bridge.loop` (:class:`~hw_bridge.loop.BridgeLoop`, :func:`~hw_bridge.loop.plan`): the ticks compiled for
  the CPU, drive modes (CSV, CST, hybrid), the takeover without a step;
* :mod:`hw_bridge.session` (:class:`~hw_bridge.session.Bridge`): CiA 402 bring-up, the run, the safe stop, the report;
* :mod:`hw_bridge.runner`, :mod:`hw_bridge.safety`, :mod:`hw_bridge.cia402`;
* transports: :mod:`hw_bridge.protocol` + :mod:`hw_bridge.udp` (UDP v1), :mod:`hw_bridge.canopen_link` (CANopen);
* :mod:`hw_bridge.sim_robot`: the simulated robot (the one module that imports the mechanism).

``pusupu bridge`` and ``pusupu sim-robot`` run them (``docs/bridge.md``).
"""
