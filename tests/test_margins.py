"""JAX loop margins (the tuner's constraints) against python-control, and their gradients."""

import json
import subprocess
import sys

import jax
import numpy as np
import pytest

from pusupu_jax import AxisLoad, ServoParams, analysis
from pusupu_jax.margins import loop_margins

SERVO = ServoParams.table1()
LOAD = AxisLoad.default()
# six different axes: faster and slower position and velocity loops than Table 1
VARIED = SERVO.replace(
    lambda2=SERVO.lambda2 * np.linspace(0.2, 1.5, 6),
    Kv=SERVO.Kv * np.linspace(0.5, 2.0, 6),
    Kp_pid=SERVO.Kp_pid * np.linspace(0.5, 3.0, 6),
)
_margins = jax.jit(loop_margins, static_argnames="mode")


@pytest.mark.parametrize("mode", ["imc", "pid"])
def test_margins_agree_with_python_control(mode):
    """Within 0.5 deg and 0.1 dB (the tuner's requirement); observed 5e-4 deg and 5e-4 dB."""
    for servo in (SERVO, VARIED):
        ours = _margins(servo, LOAD, mode=mode)
        for axis in range(6):
            ref = analysis.open_loops(servo, LOAD, axis, mode)
            for loop in ("current", "velocity", "position"):
                m = analysis.margins(ref[loop])
                assert float(ours[loop]["phase_margin_deg"][axis]) == pytest.approx(m["phase_margin_deg"], abs=0.5)
                assert float(ours[loop]["gain_margin_db"][axis]) == pytest.approx(m["gain_margin_db"], abs=0.1)
                assert float(ours[loop]["crossover_rad_s"][axis]) / (2 * np.pi) == pytest.approx(
                    m["crossover_hz"], rel=1e-3
                )


def _on_axis_0(name, value):
    base = np.asarray(getattr(SERVO, name))
    return SERVO.replace(**{name: value * np.eye(6)[0] + base * (1 - np.eye(6)[0])})


@pytest.mark.parametrize(
    "name, x, loop, key",
    [
        ("lambda2", 0.15, "position", "phase_margin_deg"),
        ("Kv", 0.015, "velocity", "gain_margin_db"),
        ("Kp_pid", 6.5, "position", "phase_margin_deg"),
    ],
)
def test_margin_gradients_match_central_differences(name, x, loop, key):
    """Margins are differentiable in the gains (axis 0): reverse mode within 1e-4 of central differences."""
    mode = "pid" if name.endswith("_pid") else "imc"

    def f(v):
        return loop_margins(_on_axis_0(name, v), LOAD, mode=mode)[loop][key][0]

    h = 1e-5 * x
    fd = (f(x + h) - f(x - h)) / (2 * h)
    ad = jax.grad(f)(x)
    assert abs(float(fd)) > 1e-3
    assert float(ad) == pytest.approx(float(fd), rel=1e-4)


# the gradient of every loop's margins in some of the gains, as JSON on stdout; run with float64 on or off
_MARGIN_GRADIENTS = """
import json, sys
from pusupu_jax.runtime import setup_jax
if sys.argv[1] == "float64":  # float32: as a notebook that skipped setup_jax, without the programs kept on disk
    setup_jax()
import jax, jax.numpy as jnp, numpy as np
from pusupu_jax import AxisLoad, ServoParams
from pusupu_jax.margins import loop_margins
servo, load = ServoParams.table1(), AxisLoad.default()
fields = ("lambda2", "T0", "Kv", "Tv", "Ki", "Ti")
def total(x):
    m = loop_margins(servo.replace(**x), load)
    assert all(v.dtype == jnp.dtype(sys.argv[1]) for v in jax.tree.leaves(m))
    return sum(jnp.minimum(loop[k], 60.0).sum() for loop in m.values() for k in ("phase_margin_deg", "gain_margin_db"))
g = jax.jit(jax.grad(total))({f: np.asarray(getattr(servo, f)) for f in fields})
jax.jit(loop_margins)(servo, load)  # the margins themselves, traced in this precision
from pusupu_jax import stability  # then the export's check, float64 in either interpreter
checked = stability.margins(servo)[0]
out = {f: np.asarray(v, dtype=float).tolist() for f, v in g.items()}
print(json.dumps(out | {"checked": [checked[loop]["phase_margin_deg"].tolist() for loop in checked]}))
"""


@pytest.mark.slow
def test_margin_gradients_are_finite_in_float32():
    """With float64 off, every margin's gradient is finite and float64's within 1e-4 of its largest (observed 6e-6).

    Far from any crossover a fast loop's |L| is tiny (1e-21 for the position loop at 1e6 rad/s), and in float32 the
    unused secant steps and angles there had overflowing derivatives: zero cotangent times inf gave NaN in every gain.
    Each precision runs in its own interpreter: JAX's float64 switch is process-wide.  Each then checks the gains as
    an export does (:func:`pusupu_jax.stability.margins`, float64 whatever the process's setting): after the margins
    were traced in float32, that check failed in XLA's verifier on a float32 grid, and now gives float64's margins.
    """
    wide, narrow = (
        {
            f: np.asarray(v)
            for f, v in json.loads(
                subprocess.run(
                    [sys.executable, "-c", _MARGIN_GRADIENTS, dtype],
                    capture_output=True,
                    text=True,
                    timeout=600,
                    check=True,
                ).stdout
            ).items()
        }
        for dtype in ("float64", "float32")
    )
    np.testing.assert_allclose(narrow.pop("checked"), wide.pop("checked"), rtol=1e-12)
    for f, w in wide.items():
        assert np.all(np.isfinite(narrow[f])), f
        scale = np.max(np.abs(w))
        assert scale > 0, f
        np.testing.assert_allclose(narrow[f], w, atol=1e-4 * scale, err_msg=f)
