"""The MuJoCo model of the mechanism, the MJX plant against C MuJoCo, and the cascade co-simulated with it."""

import contextlib
import dataclasses
import functools
import io
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from pusupu_jax import LoopRates, ServoParams
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import stack
from pusupu_jax.plant import kinematics as K
from pusupu_jax.plant import model as M
from pusupu_jax.plant.friction import slider_friction
from pusupu_jax.plant.geometry import Geometry
from pusupu_jax.plant.mjx_plant import MJXPlant
from pusupu_jax.chunked import run_chunked
from pusupu_jax.sim import rollout

with contextlib.redirect_stdout(io.StringIO()):  # MJX prints its optional GPU backends' import failures
    from mujoco import mjx

G = Geometry.default()
SERVO = ServoParams.table1()
PLANT = MJXPlant.create()
RATES = LoopRates(n_mech=5)  # 0.25 ms mechanical steps, the model's timestep
POSES = [[0.15, -0.1, 0.78, 0.05, -0.07], [-0.2, 0.0, 0.8, 0.0, 0.0], [0.05, 0.12, 0.85, -0.08, 0.03]]
HOLD_PERIODS = 3000  # 3 s, the quick experiments' horizon (their batch of two seeds is what shares the compiles)


@pytest.mark.parametrize("seed", [None, 3])
def test_model_matches_the_kinematics(seed):
    """At any assembled pose MuJoCo puts the platform where the JAX kinematics says, with every joint closed."""
    options = M.ModelOptions(kin_error_seed=seed)
    m = M.build_model(G, options)
    real = G if seed is None else M.perturbed(G, seed, options.kin_error_std)
    d = mujoco.MjData(m)
    assert m.nv == 23 and m.neq == 6
    for q in POSES:
        d.qpos[:] = M.assembled_qpos(m, real, q)
        mujoco.mj_forward(m, d)
        platform = m.body("platform").id
        np.testing.assert_allclose(d.xpos[platform], q[:3], atol=1e-12)
        np.testing.assert_allclose(d.xmat[platform].reshape(3, 3), K.platform_rotation(jnp.asarray(q)), atol=1e-12)
        assert float(M.loop_closure_residual(m, d.xpos, d.xmat)) < 1e-12
        np.testing.assert_allclose(d.qpos[M.slide_qpos(m)], K.inverse_kinematics(real, jnp.asarray(q)), atol=1e-12)


N_STEPS = 400
TORQUE = np.cumsum(np.random.default_rng(0).normal(0, 0.002, (N_STEPS, 6)), axis=0) + 0.06  # N m, near holding
# a 5 kg payload off the platform's centre, with its own inertia
OFF_CENTRE = M.ModelOptions(payload=5.0, payload_com=(0.12, -0.05, 0.04), payload_inertia=(0.02, 0.03, 0.04))


def c_mujoco_run(plant, aux, torque=TORQUE, qpos=None, model=None):
    """Open-loop torques (default :data:`TORQUE`) through C MuJoCo, with the armature the MJX plant set and the drive
    train's friction of ``aux`` (:func:`~pusupu_jax.plant.friction.slider_friction` in numpy, at each step's start).

    ``model`` defaults to the plant's own; the run starts at rest at ``qpos`` (default
    ``qpos0``).  Returns qpos and qvel after every step, the loop-closure residual [m] and
    the final ``MjData``.
    """
    m = plant.mj_model if model is None else model
    dofs = M.slide_dofs(m)
    m.dof_armature[dofs] = np.asarray(aux.model.dof_armature)[dofs]
    friction = jax.tree.map(np.asarray, aux.friction)
    d = mujoco.MjData(m)
    if qpos is not None:
        d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    qpos_out, qvel_out, res = [], [], []
    for tau in torque:
        d.qfrc_applied[:] = 0
        d.qfrc_applied[dofs] = np.asarray(aux.force_gain) * tau - slider_friction(friction, d.qvel[dofs])
        mujoco.mj_step(m, d)
        qpos_out.append(d.qpos.copy())
        qvel_out.append(d.qvel.copy())
        res.append(float(M.loop_closure_residual(m, d.xpos, d.xmat)))
    return np.array(qpos_out), np.array(qvel_out), np.array(res), d


def mjx_run(plant, aux, torque=TORQUE, qpos=None):
    """The same through ``plant`` in MJX (one jitted scan per plant, start and length); qpos and qvel after every
    step."""
    return _mjx_scan(plant, aux, jnp.asarray(torque), None if qpos is None else jnp.asarray(qpos))


@functools.partial(jax.jit, static_argnums=0)
def _mjx_scan(plant, aux, torque, qpos):
    d = plant.init(aux) if qpos is None else mjx.forward(aux.model, plant.init(aux).replace(qpos=qpos))

    def body(d, tau):
        d = plant.step(aux, d, tau)
        return d, (d.qpos, d.qvel)

    return jax.lax.scan(body, d, torque)[1]


def test_mjx_matches_c_mujoco_step_by_step_float64():
    """Same model, same inputs, Table 1's drive-train friction, 400 steps (0.1 s, sliders move up to 2.2 mm): observed
    1.0e-8 m and 3.6e-7 m/s (without friction, where the sliders move up to 15 mm: 2.3e-8 m and 7.5e-7 m/s)."""
    aux = PLANT.prepare(SERVO, None, RATES.dt_mech)
    qpos, qvel = (np.asarray(a) for a in mjx_run(PLANT, aux))
    c_qpos, c_qvel, residual, _ = c_mujoco_run(PLANT, aux)
    assert (
        np.max(np.abs(c_qpos[-1, M.slide_qpos(PLANT.mj_model)] - PLANT.mj_model.qpos0[M.slide_qpos(PLANT.mj_model)]))
        > 1e-3
    )
    assert np.max(np.abs(qpos - c_qpos)) < 1e-6
    assert np.max(np.abs(qvel - c_qvel)) < 1e-5
    assert residual.max() < 1e-5  # stiff connects: the chain stays closed to micrometres


def test_a_run_from_the_plants_start_is_a_run_from_the_whole_forward_to_the_bit():
    """MJXPlant.init computes the kinematics, centres of mass and bias forces only, not the whole ``mjx.forward``: 400
    steps from it and from the whole forward's start are the same to the bit (the step computes the rest again).  The
    holding torque that its fields give holds the machine still (test_a_run_starts_at_rest_in_every_mode)."""
    aux = PLANT.prepare(SERVO, None, RATES.dt_mech)
    for a, b in zip(mjx_run(PLANT, aux), mjx_run(PLANT, aux, qpos=PLANT.mj_model.qpos0)):
        np.testing.assert_array_equal(a, b)


def test_mjx_matches_c_mujoco_with_friction_through_reversals_and_an_off_centre_payload():
    """The friction law on every slide, MJX against C MuJoCo (float64), with a 5 kg payload off the platform's centre
    (120, -50, 40 mm, its own inertia) on the MJX plant as a variant model, and torques that reverse sliders 1-3
    (:data:`TORQUE` plus 0.1 N m at 25 Hz): 400 steps (0.1 s).

    Bounds as the frictionless comparison's, 1e-6 m and 1e-5 m/s: the friction adds no stiffness that amplifies
    rounding (its steepest slope, coulomb / v_coulomb = 2e4 N s/m on a slide's 67 kg of rotor armature and more,
    relaxes in 3 ms, 13 steps).  Observed 3.0e-8 m and 1.2e-6 m/s.  What friction changes is 1.5 mm here, 1500x
    the bound on the difference.
    """
    variant = PLANT.variant(OFF_CENTRE)
    aux = PLANT.prepare(SERVO, variant, RATES.dt_mech)
    t = np.arange(len(TORQUE)) * RATES.dt_mech
    torque = TORQUE + 0.1 * np.sin(2 * np.pi * 25 * t[:, None] + np.arange(6))
    qpos, qvel = (np.asarray(a) for a in mjx_run(PLANT, aux, torque))
    c_model = M.build_model(G, OFF_CENTRE)
    c_qpos, c_qvel, residual, _ = c_mujoco_run(PLANT, aux, torque, model=c_model)
    slider_v = c_qvel[:, M.slide_dofs(c_model)]
    assert (np.diff(np.sign(slider_v), axis=0) != 0).sum() >= 5  # through the tanh's steep part, several times
    assert np.max(np.abs(qpos - c_qpos)) < 1e-6
    assert np.max(np.abs(qvel - c_qvel)) < 1e-5
    assert residual.max() < 1e-5
    frictionless = PLANT.prepare(SERVO.replace(coulomb=np.zeros(6), viscous=np.zeros(6)), variant, RATES.dt_mech)
    assert np.max(np.abs(c_mujoco_run(PLANT, frictionless, torque, model=c_model)[0] - c_qpos)) > 1e-3


FLOAT32 = """
import json, numpy as np, jax, jax.numpy as jnp
from tests.test_mjx_plant import PLANT, SERVO, RATES, mjx_run, c_mujoco_run
aux = PLANT.prepare(SERVO, None, RATES.dt_mech)
qpos, qvel = mjx_run(PLANT, aux)
c_qpos, c_qvel, _, _ = c_mujoco_run(PLANT, aux)
print(json.dumps({"dtype": str(qpos.dtype), "qpos": float(np.abs(np.asarray(qpos) - c_qpos).max()),
                  "qvel": float(np.abs(np.asarray(qvel) - c_qvel).max())}))
"""


def test_mjx_matches_c_mujoco_in_float32():
    """Float32 (a fresh process without x64) against C MuJoCo (float64): state within 1e-4 (m, rad, m/s, rad/s).

    Observed over the 400 steps with Table 1's friction: qpos 6.3e-7, qvel 6.4e-5 (without: 3.1e-7 and 4.1e-5;
    slider 2 reverses here, through the law's steep Coulomb part).  Velocity is the tight one: the
    connect constraints turn float32 rounding of the anchor positions (~5e-8 m at 0.8 m)
    into acceleration through their stiffness ~ 1/timeconst^2, so the error scales with
    ``1/solref_timeconst^2`` (one-step qvel error 3.6e-4 at 0.5 ms, 8.9e-5 at 1 ms, 2.7e-5 at 2 ms).
    """
    r = subprocess.run(
        [sys.executable, "-c", FLOAT32],
        capture_output=True,
        text=True,
        timeout=600,
        env={"JAX_ENABLE_X64": "0", **{k: v for k, v in __import__("os").environ.items() if k != "JAX_ENABLE_X64"}},
    )
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["dtype"] == "float32"
    assert out["qpos"] < 1e-4 and out["qvel"] < 1e-4, out


def platform_move(n):
    """A 20 mm cosine move of the platform along x in 0.5 s, then hold: platform poses ``(n, 5)``."""
    t = np.arange(n) * RATES.dt_position
    x = 0.01 * (1 - np.cos(np.pi * np.clip(t / 0.5, 0, 1)))
    return np.stack([x, 0 * x, np.full(n, float(G.home[2])), 0 * x, 0 * x], axis=1)


@pytest.mark.parametrize("mode", ["imc", "pid"])
def test_cascade_drives_the_mjx_mechanism(mode):
    """All six branches position-controlled follow a 20 mm platform move and settle; the chain stays closed.  On
    the nominal machine and on one with seeded kinematic errors (seed 3), as one chunked batch of two: the program
    of the start-at-rest test below, compiled once for both.

    Observed after 3 s, worst branch: IMC 0.085 mm (nominal) and 0.086 mm (seeded), PID 0.033 and 0.032 mm, from
    the reference (branch travel up to 4.1 mm).  The drive train's friction slows the settling: after 1.5 s PID is
    still 0.64 mm off (0.26 mm without friction), IMC 0.18 mm (0.012 mm).  Closure residual 1.1 um (IMC) and 0.9 um
    (PID) against RMS branch errors of 0.17 and 0.46 mm (the bound, 1 %, is 1.6x the IMC run's ratio; the run is
    deterministic).
    """
    from pusupu_jax.machine import machine_plant, machine_reference

    plant = machine_plant()
    ref = np.asarray(machine_reference(SERVO, platform_move(3000), mode, rates=RATES))
    models = stack([plant.variant(M.ModelOptions()), plant.variant(M.ModelOptions(kin_error_seed=3))])
    trace, _ = run_chunked(SERVO, models, np.stack([ref, ref]), plant=plant, rates=RATES, outer=mode)
    s_ref = ref * float(SERVO.lead[0]) / (2 * np.pi)
    travel = np.max(np.abs(s_ref))
    assert travel > 3e-3
    for k in range(2):
        err = np.asarray(trace.position[k]) - s_ref
        assert np.max(np.abs(err[-1])) < 0.1 * travel, (k, np.max(np.abs(err[-1])))
        rms = np.sqrt(np.mean(err**2))
        residual = np.asarray(trace.observation["closure_residual"][k])
        assert residual.max() < 0.01 * rms, (k, residual.max(), rms)


def test_machine_rejects_a_path_outside_the_workspace_before_running():
    from pusupu_jax.machine import simulate_machine
    from pusupu_jax.plant.geometry import GeometryError

    path = np.repeat(G.home[None], 10, axis=0)
    path[5, 0] = 0.6
    with pytest.raises(GeometryError, match="pose 5 .*(unreachable|out of stroke|near-singular)"):
        simulate_machine(SERVO, path)


def test_one_newton_iteration_is_the_converged_solve_without_contacts():
    """Equality constraints only: the soft-constraint problem is quadratic, one Newton step solves it (C MuJoCo)."""
    aux = PLANT.prepare(SERVO, None, RATES.dt_mech)
    runs = []
    for iterations, tolerance in ((1, 1e-8), (100, 1e-12)):
        m = M.build_model(G, M.ModelOptions(solver_iterations=iterations))
        m.opt.tolerance = tolerance
        runs.append(c_mujoco_run(PLANT, aux, model=m)[0])
    assert np.max(np.abs(runs[0] - runs[1])) < 1e-12


CONTACT_PLANT = MJXPlant.create(G, M.ModelOptions(contacts=True))


def test_without_contacts_the_line_search_would_change_nothing():
    """The model without contacts takes no line-search iterations (:data:`M.LS_ITERATIONS_CONTACTS` with contacts):
    its equality constraints' cost is quadratic along the Newton direction, so the search starts at its minimum.  With
    MuJoCo's 4 iterations instead, 400 steps through C MuJoCo are the same to the bit, and 400 steps of two torque
    sequences vmapped through MJX (where each iteration's conditional computes both branches) the same to rounding as
    each run alone without them (:func:`mjx_run`, the program of the tests above).  The tuner's objective and gradients
    over its iterations: ``docs/benchmarks.md``."""
    assert PLANT.mj_model.opt.ls_iterations == 0 and CONTACT_PLANT.mj_model.opt.ls_iterations == 4
    aux = PLANT.prepare(SERVO, None, RATES.dt_mech)
    aux4 = dataclasses.replace(aux, model=aux.model.replace(opt=aux.model.opt.replace(ls_iterations=4)))
    searched = M.build_model(G, M.ModelOptions())
    searched.opt.ls_iterations = 4
    for a, b in zip(
        c_mujoco_run(PLANT, aux, model=M.build_model(G, M.ModelOptions()))[:2],
        c_mujoco_run(PLANT, aux, model=searched)[:2],
    ):
        np.testing.assert_array_equal(a, b)
    torques = jnp.stack([TORQUE, TORQUE[::-1]])

    def run(aux, torque):
        return jax.lax.scan(lambda d, tau: (PLANT.step(aux, d, tau), None), PLANT.init(aux), torque)[0].qpos

    searched = jax.jit(jax.vmap(run, (None, 0)))(aux4, torques)
    # to rounding (XLA compiles the two programs differently): observed 1.4e-16 m
    for k, torque in enumerate(torques):
        np.testing.assert_allclose(searched[k], mjx_run(PLANT, aux, torque)[0][-1], rtol=0, atol=1e-15)


def _above_the_surface(gap):
    """qpos of the home pose lowered until the tool sphere is ``gap`` [m] above the work surface (joints closed)."""
    m = CONTACT_PLANT.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)  # qpos0 is the home pose
    tool, surface = m.geom("tool"), m.geom("surface")
    clearance = (d.geom_xpos[tool.id][2] - tool.size[0]) - (d.geom_xpos[surface.id][2] + surface.size[2])
    pose = np.array(G.home, dtype=float)
    pose[2] -= clearance - gap
    return M.assembled_qpos(m, G, pose)


def test_contacts_stop_the_platform_on_the_work_surface_as_in_c_mujoco():
    """``ModelOptions(contacts=True)``: released with the motors off 1 mm above the surface, the machine falls,
    the tool lands 48 ms in and the surface holds it.

    MJX against C MuJoCo through the impact (float64, 400 steps): observed 9.4e-13 m and 9.8e-10 m/s
    (bounds 1e-9 m and 1e-7 m/s: 1000x and 100x headroom for rounding that the impact amplifies).
    One Newton iteration is still the converged solve with this single contact: observed 5e-15 m
    against 100 iterations.
    """
    aux = CONTACT_PLANT.prepare(SERVO, None, RATES.dt_mech)
    q0, off = _above_the_surface(1e-3), np.zeros_like(TORQUE)
    qpos, qvel = (np.asarray(a) for a in mjx_run(CONTACT_PLANT, aux, off, q0))
    c_qpos, c_qvel, _, landed = c_mujoco_run(CONTACT_PLANT, aux, off, q0)
    assert np.max(np.abs(qpos - c_qpos)) < 1e-9
    assert np.max(np.abs(qvel - c_qvel)) < 1e-7
    m = CONTACT_PLANT.mj_model
    force = np.zeros(6)
    assert landed.ncon == 1
    mujoco.mj_contactForce(m, landed, 0, force)
    assert force[0] > 100.0  # N along the normal: the surface carries the machine
    _, _, _, free = c_mujoco_run(CONTACT_PLANT, aux, off, q0, model=M.build_model(G, M.ModelOptions()))
    platform = m.body("platform").id
    assert free.xpos[platform][2] < landed.xpos[platform][2] - 1e-3  # without the surface it falls further
    converged = M.build_model(G, M.ModelOptions(contacts=True, solver_iterations=100))
    converged.opt.tolerance = 1e-12
    assert np.max(np.abs(c_qpos - c_mujoco_run(CONTACT_PLANT, aux, off, q0, model=converged)[0])) < 1e-12


@pytest.mark.slow
def test_gradient_through_contact_matches_central_differences():
    """d(mean platform height over the last 25 ms of 100 ms) / d(motor torque, the same on every axis) with the
    tool pressed on the surface (C MuJoCo: in contact at 75 ms and at 100 ms): reverse mode against
    central differences (h = 1e-5 N m), observed 4e-10 relative (7e-8 at h = 1e-4, 2e-7 at 1e-6: truncation
    and round-off of the differences).  Bound 1e-6.
    """
    aux = CONTACT_PLANT.prepare(SERVO, None, RATES.dt_mech)
    q0 = jnp.asarray(_above_the_surface(1e-3))
    platform = CONTACT_PLANT.mj_model.body("platform").id
    n, u, h = len(TORQUE), 0.02, 1e-5

    def height(tau):
        def body(d, _):
            d = CONTACT_PLANT.step(aux, d, jnp.full(6, tau))
            return d, d.xpos[platform, 2]

        d0 = mjx.forward(aux.model, CONTACT_PLANT.init(aux).replace(qpos=q0))
        return jnp.mean(jax.lax.scan(body, d0, None, length=n)[1][-n // 4 :])

    value_and_grad = jax.jit(jax.value_and_grad(height))
    for steps in (3 * n // 4, n):
        assert c_mujoco_run(CONTACT_PLANT, aux, np.full((steps, 6), u), np.asarray(q0))[3].ncon == 1
    ad = float(value_and_grad(u)[1])
    fd = (float(value_and_grad(u + h)[0]) - float(value_and_grad(u - h)[0])) / (2 * h)
    assert fd > 0.0  # more holding torque, less weight on the surface: the platform sits higher
    assert abs(ad - fd) <= 1e-6 * abs(fd), (ad, fd)


def _short_path(n=50):
    """Platform poses of a 5 mm cosine move along x in ``n`` position periods (50 ms)."""
    x = 0.005 * (1 - np.cos(np.pi * np.arange(n) / (n - 1)))
    return np.stack([x, 0 * x, np.full(n, float(G.home[2])), 0 * x, 0 * x], axis=1)


AXIS_0 = ("Kv", "Tv", "coulomb", "viscous", "v_coulomb")  # velocity loop and drive-train friction of axis 0


@pytest.mark.slow
def test_every_objective_term_has_the_gradient_of_central_differences():
    """Reverse mode through cascade + MJX, hybrid mode on the machine (50 ms: 200 MJX steps, 1000 current ticks,
    float64; axes 1-5 in the IMC position loop, axis 6 in force control), for every term of pusupu_jax.objectives:
    d/d(log gain) for the tuner's default fields (shared lambda1, lambda2, T0 and m6, c6, g); d/d(relative change)
    of axis 0's velocity PI and drive-train friction (Kv, Tv, coulomb, viscous, v_coulomb: values of the one compiled
    program, as the gains and the model are); and d/d(platform mass) (what identification fits of a payload), whose
    derivative includes that of the torque the run starts holding the machine with.  Reverse mode against central
    differences (steps of 1e-3 in log gain, 1e-4 relative, 1e-4 of the platform's mass): relative error <= 1e-3, or
    within 1e-7 of the term's size.  Observed: 1e-9 to 1e-5 on every term of every input with Table 1's friction (the
    mass 1e-9, Kv 1e-8, the friction 1e-8 to 4e-5), except the gains whose effect on a 50 ms run is some 1e-10 of the
    term (g: up to 3.5e-3, inside the 1e-7 floor).  Each input has a term whose derivative is non-zero and agrees to
    1e-3 relative.

    One compiled program serves it all: the Jacobian with the terms' values (``has_aux``), called at the moved inputs
    for the differences.  Forward mode (what identification's ``jacfwd`` runs) has no program of its own here: JAX
    derives reverse mode by linearising with the same forward-mode rules and transposing, so a reverse-mode
    derivative that matches central differences has run each of those rules on this path (a forward-mode program
    beside it agreed with reverse mode to 1e-9 of each term's size, and cost 23 s more to trace and compile).  An
    IMC-mode program of its own would cost another compile, 45 s."""
    from pusupu_jax import objectives
    from pusupu_jax.machine import machine_reference
    from pusupu_jax.tune.space import Space

    path = _short_path()
    ref = machine_reference(SERVO, path, "hybrid", rates=RATES)
    space = Space.create(("imc", "hybrid"), SERVO, HybridGains())
    platform = PLANT.mj_model.body("platform").id
    model, mass = PLANT.mjx_model, PLANT.mjx_model.body_mass

    def terms(x):
        servo, hybrid = space.apply(x["z"])
        servo = servo.replace(**{n: jnp.asarray(getattr(servo, n), float).at[0].multiply(1.0 + x[n]) for n in AXIS_0})
        m = model.replace(body_mass=mass.at[platform].add(x["mass"]))
        trace = rollout(servo, m, ref, plant=PLANT, rates=RATES, outer="hybrid", hybrid=hybrid)
        return objectives.terms(trace, servo, jnp.asarray(path), RATES.dt_position, sharpness_force=1.0)

    x0 = {"z": space.z0(), **{n: jnp.zeros(()) for n in AXIS_0}, "mass": jnp.zeros(())}
    steps = {n: 1e-4 for n in AXIS_0} | {"mass": 1e-4 * float(mass[platform])}
    jacobian = jax.jit(jax.jacrev(lambda x: (terms(x),) * 2, has_aux=True))  # (d terms / d x, terms)
    jac, at_start = jacobian(x0)

    def value(x):
        return jacobian(x)[1]

    def moved(name, by):  # x0 with one input moved by ``by``: a tuner field (in z) or an input of its own
        if name in x0["z"]:
            return x0 | {"z": x0["z"] | {name: x0["z"][name] + by}}
        return x0 | {name: x0[name] + by}

    inputs = [*x0["z"], *AXIS_0, "mass"]
    report = []
    for name in inputs:
        h = steps.get(name, 1e-3)
        plus, minus = value(moved(name, h)), value(moved(name, -h))
        for term in objectives.TERMS:
            fd = (float(plus[term]) - float(minus[term])) / (2 * h)
            ad = float(jac[term]["z"][name] if name in x0["z"] else jac[term][name])
            size = abs(float(at_start[term]))
            report.append((name, term, ad, fd, size, h))
            # 1e-3 relative, or 1e-7 of the term's own size for gradients too small to matter to the tuner
            # (where central differences see the rollout's round-off: force_peak vs lambda1 is 1e-6 relative)
            assert abs(ad - fd) <= 1e-3 * abs(fd) + 1e-7 * size, (name, term, ad, fd)
    for name in inputs:  # each input's derivative is exercised: some term moves and agrees
        assert any(fd != 0.0 and abs(ad - fd) <= 1e-3 * abs(fd) for n, _, ad, fd, _, _ in report if n == name), name
    assert sum(abs(fd) > 1e-3 * size for _, _, _, fd, size, _ in report) >= 5  # real gradients


def test_model_variants_vmapped_equal_their_own_plants():
    """Seeded kinematic errors with a payload, as an MJXPlant.variant model vmapped beside the nominal one through one
    compiled (chunked) run, give the trajectory of a plant built for them, whose model is a constant of its own
    program (observed 4e-16 m, 8e-12 N m over 0.1 s of the p2p path).  The nominal member moves differently: the
    batch's program reads each member's model.
    """
    from pusupu_jax.machine import machine_reference
    from pusupu_jax.trajectories import platform_path

    options = M.ModelOptions(kin_error_seed=3, payload=5.0)
    path = platform_path("p2p", G.home, RATES)[:100]
    ref = machine_reference(SERVO, path, "pid", rates=RATES)
    models = stack([PLANT.variant(options), PLANT.variant(M.ModelOptions())])
    # the chunked batch of simulate_scenarios (the PID + feedforward's programs of the start-at-rest test, at Kff = 0)
    batch, _ = run_chunked(SERVO, models, np.stack([ref, ref]), plant=PLANT, rates=RATES, outer="pid")
    own = MJXPlant.create(G, options)
    trace = jax.jit(lambda r: rollout(SERVO, None, r, plant=own, rates=RATES, outer="pid"))(ref)
    np.testing.assert_allclose(batch.position[0], trace.position, atol=1e-12)
    np.testing.assert_allclose(batch.torque[0], trace.torque, atol=1e-9)
    np.testing.assert_allclose(
        batch.observation["closure_residual"][0], trace.observation["closure_residual"], atol=1e-12
    )
    assert np.max(np.abs(np.asarray(batch.torque[0] - batch.torque[1]))) > 1e-3  # the variant does differ


def test_a_payload_is_a_variant_of_the_same_structure_and_adds_its_mass():
    """Payloads of any mass, centre of mass and inertia build models of the same sizes and array shapes (so they vmap
    through one compiled rollout); the machine's total mass rises by the payload's (observed to 7e-15 kg)."""
    base = M.build_model(G, M.ModelOptions())
    sizes = ("nq", "nv", "nbody", "neq", "ngeom")
    for options in (M.ModelOptions(payload=5.0), OFF_CENTRE, M.ModelOptions(payload=80.0, payload_com=(0, 0, -0.3))):
        m = M.build_model(G, options)
        assert [getattr(m, n) for n in sizes] == [getattr(base, n) for n in sizes]
        assert mujoco.mj_getTotalmass(m) - mujoco.mj_getTotalmass(base) == pytest.approx(options.payload, abs=1e-12)
        variant = PLANT.variant(options)
        assert jax.tree.map(jnp.shape, variant) == jax.tree.map(jnp.shape, PLANT.mjx_model)
        platform = PLANT.mj_model.body("platform").id
        assert float(variant.body_subtreemass[platform] - PLANT.mjx_model.body_subtreemass[platform]) == pytest.approx(
            options.payload, abs=1e-12
        )


def test_new_masses_give_the_constants_mujocos_compiler_derives_from_them():
    """MJXPlant.with_masses (the identification's payload, set into a model built for another) gives the subtree
    masses, the joint-space inertia's diagonal and the inverse weights of the model MuJoCo compiles with that payload
    (observed to 2e-15), where the masses set alone leave them at the other payload's (3 against 5 kg: 0.09 apart
    in body_invweight0, on values up to 2.1)."""
    derived = ("body_subtreemass", "dof_M0", "body_invweight0", "dof_invweight0")
    start = PLANT.variant(dataclasses.replace(OFF_CENTRE, payload=3.0, payload_com=(0.0, 0.0, 0.0)))
    target = PLANT.variant(OFF_CENTRE)
    got = jax.jit(PLANT.with_masses)(start, target.body_mass, target.body_pos)
    stale = start.replace(body_mass=target.body_mass, body_pos=target.body_pos)
    for name in derived:
        np.testing.assert_allclose(getattr(got, name), getattr(target, name), rtol=0, atol=1e-12, err_msg=name)
    assert max(float(jnp.abs(getattr(stale, n) - getattr(target, n)).max()) for n in derived) > 0.05


def test_a_payloads_weight_and_centre_of_mass_show_in_the_holding_forces():
    """The slider forces [N] that hold the machine at home (level platform; vertical rails), with a 5 kg payload:

    * their sum rises by the payload's weight m g wherever its centre of mass is (a vertical translation moves every
      slider by as much as the platform, so the virtual work of the holding forces is the payload's);
    * centred, each branch carries a sixth of it, as a platform heavier by 5 kg does;
    * 100 mm straight above the centre, or with inertia, the forces are the centred payload's (gravity along the
      platform's axis; no moment at rest);
    * 100 mm off along +x, the branches on the +x side carry more than those on the -x side, and along -x the forces
      are the +x ones mirrored through the y-z plane (the geometry's mirror symmetry maps branches 0-5 onto 1, 0, 5,
      4, 3, 2).

    Bounds 1e-9 of the forces without payload (63 N; exact but for rounding): observed 1e-15 at most.
    """

    @jax.jit
    def hold(model):
        aux = PLANT.prepare(SERVO, model, RATES.dt_mech)
        return PLANT.holding_torque(aux, PLANT.statics(aux, PLANT.init(aux))) * aux.force_gain

    def force(options=M.ModelOptions(), geom=None):
        return np.asarray(hold(PLANT.variant(options, geom)))

    m, g = 5.0, 9.81
    empty, centred = force(), force(M.ModelOptions(payload=m))
    tol = 1e-9 * np.abs(empty).max()
    np.testing.assert_allclose(centred - empty, m * g / 6, atol=tol)
    np.testing.assert_allclose(force(geom=G.replace(platform_mass=np.asarray(G.platform_mass) + m)), centred, atol=tol)
    for same in ((0, 0, 0.1), (0, 0, 0)), ((0, 0, 0), (0.1, 0.2, 0.25)):
        np.testing.assert_allclose(
            force(M.ModelOptions(payload=m, payload_com=same[0], payload_inertia=same[1])), centred, atol=tol
        )
    plus, minus = (force(M.ModelOptions(payload=m, payload_com=(x, 0, 0))) for x in (0.1, -0.1))
    for off in (plus, minus, force(OFF_CENTRE)):
        assert np.sum(off - empty) == pytest.approx(m * g, abs=6 * tol)
    x = np.asarray(G.platform_points)[:, 0]
    assert (plus - centred)[x > 0.15].min() > 0.5 * m * g / 6 and (plus - centred)[x < -0.15].max() < -0.5 * m * g / 6
    np.testing.assert_allclose(minus, plus[[1, 0, 5, 4, 3, 2]], atol=tol)


def test_every_bodys_centre_of_mass_is_where_the_model_puts_it():
    """In C MuJoCo at home, in each body's own frame: an off-centre payload's centre of mass at its ``payload_com``
    in the platform's (the payload body sits there), each rod's half its length along the rod, the passive leg's
    tubes at their middles (the lower one above the base's U joint, the upper one below the platform's), every
    other body's at its frame's origin.  MuJoCo's compiler copies a body's position into an inertial position left
    undefined, which put every such centre of mass at twice the body's position (a payload at 2 x its com).  Exact
    but for rounding (1e-12 m)."""
    m = M.build_model(G, OFF_CENTRE)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)

    def com_in(body: str, frame: str) -> np.ndarray:
        b, f = m.body(body).id, m.body(frame).id
        return d.xmat[f].reshape(3, 3).T @ (d.xipos[b] - d.xpos[f])

    np.testing.assert_allclose(com_in("payload", "platform"), OFF_CENTRE.payload_com, atol=1e-12)
    np.testing.assert_allclose(com_in("upu_lower", "upu_lower"), [0, 0, M.UPU_TUBE / 2], atol=1e-12)
    np.testing.assert_allclose(com_in("upu_upper", "upu_upper"), [0, 0, -M.UPU_TUBE / 2], atol=1e-12)
    for i in range(6):
        length = float(np.asarray(G.rod_lengths)[i])
        np.testing.assert_allclose(com_in(f"rod_{i}", f"rod_{i}"), [0, 0, length / 2], atol=1e-12)
        np.testing.assert_allclose(com_in(f"slider_{i}", f"slider_{i}"), 0.0, atol=1e-12)
    np.testing.assert_allclose(com_in("platform", "platform"), 0.0, atol=1e-12)


@pytest.mark.parametrize(
    "options, message",
    [
        (M.ModelOptions(payload=-1.0), r"ModelOptions.payload: expected a finite mass >= 0 \[kg\], got -1.0"),
        (M.ModelOptions(payload=float("nan")), r"ModelOptions.payload: expected a finite mass >= 0 \[kg\], got nan"),
        (
            M.ModelOptions(payload=1.0, payload_com=(0.0, float("inf"), 0.0)),
            r"ModelOptions.payload_com: expected a finite",
        ),
        (
            M.ModelOptions(payload=1.0, payload_com=(0.0, 0.0)),
            r"ModelOptions.payload_com: expected a finite \(x, y, z\)",
        ),
        (
            M.ModelOptions(payload=1.0, payload_inertia=(0.1, -0.1, 0.1)),
            r"payload_inertia: expected three finite principal "
            r"moments >= 0 \[kg m\^2\], got \(0.1, -0.1, 0.1\)",
        ),
        (
            M.ModelOptions(payload=1.0, payload_inertia=(0.1, 0.1, 0.3)),
            r"payload_inertia: expected principal moments of a "
            r"rigid body \(each at most the sum of the other two\)",
        ),
        (
            M.ModelOptions(payload=0.0, payload_inertia=(0.1, 0.1, 0.1)),
            r"payload_inertia: expected \(0, 0, 0\) without a "
            r"payload mass",
        ),
    ],
)
def test_a_payload_that_is_no_rigid_body_is_refused_in_one_line(options, message):
    with pytest.raises(ValueError, match=message) as e:
        M.build_model(G, options)
    assert "\n" not in str(e.value)


def _hold(periods=HOLD_PERIODS):
    """Two scenarios, the batch size of pusupu_jax.experiments.p2p's quick run (two seeds): p2p's first second (padded)
    and
    holding still.  run_chunked's programs depend on the batch size, not on the horizon."""
    from pusupu_jax.machine import Scenario
    from pusupu_jax.trajectories import platform_path

    return [
        Scenario(platform_path("p2p", G.home, RATES)[:1000]),
        Scenario(np.repeat(G.home[None], periods, axis=0), M.ModelOptions(kin_error_seed=3)),
    ]


def test_the_spherical_joints_jacobian_is_the_derivative_of_their_gap():
    """The constraint Jacobian behind the start at rest (MuJoCo's point Jacobians, MJXPlant._connect_jacobian)
    against forward-mode autodiff of the anchors' gap through mjx.kinematics, on a machine with seeded errors at a
    pose off home: observed 2e-16."""
    aux = PLANT.prepare(SERVO, PLANT.variant(M.ModelOptions(kin_error_seed=3)), RATES.dt_mech)
    qpos = jnp.asarray(M.assembled_qpos(PLANT.mj_model, G, POSES[0]))

    @jax.jit  # one compile, not MJX's thousands of operations dispatched (and compiled) one by one
    def both(a, q):
        model = a.model
        d = mjx.forward(model, PLANT.init(a).replace(qpos=q))

        def gap(q):
            k = mjx.kinematics(model, d.replace(qpos=q))
            return M.connect_gap(PLANT.mj_model, k.xpos, k.xmat, model.eq_data).reshape(-1)

        return PLANT._connect_jacobian(model, d), jax.jacfwd(gap)(q)

    connect, autodiff = both(aux, qpos)
    np.testing.assert_allclose(connect, autodiff, atol=1e-12)


def test_printed_form_started_as_before_reproduces_the_old_figures():
    """eq. 9 as printed (imc_form printed) with every controller state zero at t = 0 (start zero): the first second
    of the p2p path gives the figures of the code before the full form and the start at rest existed, to rounding;
    and a machine told to hold still sags, as it did.  Without the drive train's friction, which the machine did not
    have then.

    The code of commit 6db0911 (simulate_machine, Table 1, IMC) gave RMS 2.065628150536743 mm, max
    4.578009063579978 mm and branch force peaks of 79.305 N (the sag under gravity in the first 0.2 s) on the model
    of its day, whose passive leg's upper tube had its centre of mass 0.8 m above the platform (MuJoCo's compiler
    copied the body's position into the inertial one; docs/geometry.md).  The figures below are that run on the
    corrected model: RMS 0.27 % lower, the same force peaks to 1e-6.  Tolerance 1e-9 relative: the vmapped batch
    reorders some sums.  Observed sag when holding still: 1.06 mm in 0.2 s.
    """
    from pusupu_jax.machine import simulate_scenarios

    before = SERVO.replace(imc_form="printed", coulomb=np.zeros(6), viscous=np.zeros(6))
    (run, _), (_, hold) = simulate_scenarios(before, _hold(), mode="imc", start="zero")
    r = run.metrics
    assert r.rms_tracking_error_mm == pytest.approx(2.060113219419881, rel=1e-9)
    assert r.max_tracking_error_mm == pytest.approx(4.570160883971736, rel=1e-9)
    np.testing.assert_allclose(
        r.branch_force_peak_n,
        [79.30529578607529, 79.30538589896243, 79.3051597365802, 79.3051927202997, 79.3053582824391, 79.30523518609387],
        rtol=1e-9,
    )
    sag = np.linalg.norm(hold["platform"][:200] - hold["platform"][0], axis=1).max()
    assert sag > 1e-4, sag


@pytest.mark.parametrize("mode", ["imc", "pid", "pid_ff", "hybrid"])
def test_a_run_starts_at_rest_in_every_mode(mode):
    """Holding still from t = 0 (start rest: the drives carry the machine's weight with preloaded currents and
    integrators), the platform moves less than 10 um in the first 0.2 s, and over the whole 3 s, in every mode,
    with seeded kinematic errors (seed 3).  Observed: 0.1 um or less (the soft spherical joints settling).
    """
    from pusupu_jax.machine import simulate_scenarios

    _, (result, arrays) = simulate_scenarios(SERVO, _hold(), mode=mode)
    moved = np.linalg.norm(arrays["platform"] - arrays["platform"][0], axis=1) * 1e3  # mm
    assert moved[:200].max() < 10e-3, (mode, moved[:200].max())
    assert moved.max() < 10e-3, (mode, moved.max())


CONTACT_SCENES = {  # the contact experiments' scenes and solver settings (experiments/contact.py)
    "peg": (
        M.ModelOptions(
            contacts=True, scene="peg_in_hole", hole_offset=(0.0048, 0.0), solver_iterations=4, cone="elliptic"
        ),
        {"hole_chamfer_1", "hole_wall_1"},
    ),
    "tilted surface": (
        M.ModelOptions(
            contacts=True, scene="surface", surface_tilt=0.01, friction=0.2, solver_iterations=4, cone="elliptic"
        ),
        {"surface"},
    ),
}


def _over_first_contact(plant, gap):
    """qpos of the home pose lowered until the tool is ``gap`` [m] over its first contact with the scene."""
    m = plant.mj_model
    d = mujoco.MjData(m)
    lo, hi = 0.0, 0.03  # m of descent: no contact at lo, contact at hi
    for _ in range(40):
        mid = (lo + hi) / 2
        d.qpos[:] = M.assembled_qpos(m, G, np.asarray(G.home) - [0, 0, mid, 0, 0])
        mujoco.mj_forward(m, d)
        lo, hi = (lo, mid) if d.ncon else (mid, hi)
    return M.assembled_qpos(m, G, np.asarray(G.home) - [0, 0, lo - gap, 0, 0])


def _c_contact_force(m, d):
    """The force [N] on the tool from every contact of C MuJoCo's ``d`` (world axes), as ``mj_contactForce`` gives."""
    tool, total = m.geom("tool").id, np.zeros(3)
    for k, contact in enumerate(d.contact[: d.ncon]):
        local = np.zeros(6)
        mujoco.mj_contactForce(m, d, k, local)
        world = local[:3] @ contact.frame.reshape(3, 3)
        total += world if contact.geom[1] == tool else -world
    return total


@pytest.mark.parametrize("scene", sorted(CONTACT_SCENES))
def test_the_contact_scenes_land_as_in_c_mujoco(scene):
    """The contact experiments' scenes with their solver (four Newton iterations, elliptic cone), motors off: the
    machine drops 1 mm onto the scene (about step 190) and 400 steps (0.1 s) run.  Peg: the hole 4.8 mm off, so
    that the tip lands mid-chamfer, slides down it and wedges between the chamfer and the wall.  Tilted surface:
    the tool lands on the 10 mrad slope (friction 0.2) and the surface carries the machine.

    MJX against C MuJoCo (float64): qpos and qvel along the whole run, observed 1.2e-9 m and 9.7e-8 m/s (peg),
    3.1e-11 m and 1.9e-9 m/s (surface); bounds 1e-7 m and 1e-5 m/s: 100x headroom for rounding that the impact
    amplifies.  The contact force on the tool every 25 steps at C's state (MJX's :meth:`MJXPlant.contact_force`
    against the sum of ``mj_contactForce``): observed within 3.6e-6 (peg, 570-870 N) and 4.8e-8 (surface) of its
    magnitude; bound 1e-4.
    """
    options, expected = CONTACT_SCENES[scene]
    plant = MJXPlant.create(G, options)
    aux = plant.prepare(SERVO, None, RATES.dt_mech)
    q0, off = _over_first_contact(plant, 1e-3), np.zeros_like(TORQUE)
    qpos, qvel = (np.asarray(a) for a in mjx_run(plant, aux, off, q0))
    c_qpos, c_qvel, _, _ = c_mujoco_run(plant, aux, off, q0)
    assert np.max(np.abs(qpos - c_qpos)) < 1e-7
    assert np.max(np.abs(qvel - c_qvel)) < 1e-5
    m = plant.mj_model
    contact_force = jax.jit(
        lambda model, q, v: plant.contact_force(model, mjx.forward(model, mjx.make_data(model).replace(qpos=q, qvel=v)))
    )
    touched, worst = set(), 0.0
    for k in range(24, len(TORQUE), 25):
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = c_qpos[k], c_qvel[k]
        mujoco.mj_forward(m, d)
        c_force = _c_contact_force(m, d)
        force = np.asarray(contact_force(aux.model, c_qpos[k], c_qvel[k]))
        touched |= {m.geom(c.geom[1]).name for c in d.contact[: d.ncon]}
        if d.ncon:
            worst = max(worst, np.linalg.norm(force - c_force) / np.linalg.norm(c_force))
        else:
            assert np.all(force == 0.0)
    assert touched == expected
    assert worst < 1e-4
