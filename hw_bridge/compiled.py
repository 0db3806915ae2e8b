"""Pure step functions compiled before the first cycle on the CPU over flat float64 vectors (host-side).

Calling a jitted function costs a flatten of every argument pytree and a transfer per leaf: a
cascade's state is dozens of leaves (the MJX machine's state, hundreds), which cost more than the
step itself at kilohertz rates.  :class:`FlatStep` packs the state and each input into one vector
(``jax.flatten_util.ravel_pytree``; integer leaves round-trip exactly through float64), unpacks them
inside the compiled function, and keeps the state on the device between calls, so one cycle is one
call with a few small arrays.  What is fixed for a run (a drive's coefficients, the gains) is closed
over: constants of the compiled step, not arguments.  As one argument vector (4.4 kB for a drive's
coefficients) it made XLA's CPU runtime run the step's parts on its thread pool, which it does when
a buffer passes 512 bytes, and the calling thread woke the pool and waited for it twice a call: the
simulated robot's drive step took 73 us a call at p50 in a tight loop, and 15 us with no hand-off as
constants.  The call goes through ``jax.jit``'s C++ dispatch (an ahead-of-time ``Compiled`` object
dispatches in Python, about 40 us slower here); the construction compiles and runs it once, so no
cycle ever compiles.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.flatten_util import ravel_pytree


def cpu():
    """The CPU device (the loops run there even when a GPU is present).

    The real-time processes (``pusupu bridge``, ``pusupu sim-robot``) set JAX up with
    ``setup_jax(synchronous_cpu=True)``: asynchronous dispatch may run a step on a pool thread while the cycle's
    thread waits, and with the cycle's thread at SCHED_FIFO on one pinned CPU that thread would wait behind it;
    synchronous dispatch keeps the step on the real-time thread.  (Not measured apart: the 80 ms first steps seen
    while building this were compiles, of calls made outside the warm-up's ``default_device`` context; see
    :class:`FlatStep`.)
    """
    return jax.devices("cpu")[0]


class FlatStep:
    """``fn(*consts, state, *inputs) -> (state, out)`` as ``step(state_flat, *inputs_flat) -> (state_flat, out_flat)``.

    ``consts``: pytrees fixed for the run (a drive's coefficients, gains), constants of the compiled step;
    ``state`` and ``inputs``: example pytrees of the shapes the step takes.  Compiled and run once
    (warm-up) at construction.
    """

    def __init__(self, fn, consts: tuple, state, inputs: tuple):
        device = cpu()
        consts = jax.device_put(consts, device)
        state_flat, self.unravel_state = ravel_pytree(state)
        in_flats = [ravel_pytree(x) for x in inputs]

        def flat(state, *ins):
            s = self.unravel_state(state)
            ins = [un(a) for (_, un), a in zip(in_flats, ins)]
            s2, out = fn(*consts, s, *ins)
            return ravel_pytree(s2)[0], ravel_pytree(out)[0]

        self.state = jax.device_put(state_flat, device)
        self._exe = jax.jit(flat)  # called with committed CPU arrays: it compiles and runs there
        # compile and warm up before the first cycle, as the cycles call it (a default_device context would be part
        # of the compile's key: the first cycle would compile again)
        self(self.state, *[np.asarray(f) for f, _ in in_flats])

    def __call__(self, state, *inputs):
        """One step: ``(state_flat (device), out (numpy))``."""
        s, out = self._exe(state, *[np.ravel(x) for x in inputs])
        return s, np.asarray(out)
