"""The simulated robot (``pusupu sim-robot``): the MJX machine and its drives behind the bridge's UDP or CANopen
transport, with faults on demand (:mod:`pusupu_jax.sim_robot.robot`)."""
