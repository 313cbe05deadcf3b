"""Dynamics (issue 3 "must show"): energy conservation, holding commands, inverse/forward
consistency, the mass matrix, and an independent numeric-Lagrangian formulation."""
from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType
from typing import Any

import casadi as ca
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import inverse_kinematics, jacobian
from falcon_plan.model.params import ACRA2009
from falcon_plan.model.symbolic import DynamicsFunctions, dynamics_functions
from falcon_plan.model.workspace import DEFAULT_LIMITS, in_workspace, sample_workspace


def _load_reference() -> ModuleType:
    """The plain-numpy reference (tests/model/numpy_reference.py), loaded by path because the
    test tree is not a package."""
    spec = importlib.util.spec_from_file_location("falcon_numpy_reference",
                                                  Path(__file__).with_name("numpy_reference.py"))
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(module)
    return module


ref = _load_reference()
NOMINAL_EFF = FalconModel(ACRA2009).effect_vector


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(b))


# --- energy conservation ---------------------------------------------------------------------

def _simulate(fns: DynamicsFunctions, p0, v0, duration_s: float, spring_Nm_rad: float = 0.0):
    """Integrate the unforced dynamics (forward_dynamics_torque with zero motor torque), or
    with a conservative spring tau = -k (theta1 - theta1(p0)) at the pivots, using DOP853 at
    rtol 1e-11. Returns the solution and a function giving the total energy along it [J]."""
    p, v = ca.SX.sym("p", 3), ca.SX.sym("v", 3)
    theta1 = fns.leg_angles(p, NOMINAL_EFF)[0]
    theta1_0 = inverse_kinematics(p0).theta1
    tau = -spring_Nm_rad * (theta1 - theta1_0)
    acc = fns.forward_dynamics_torque(p, v, tau, NOMINAL_EFF)
    kinetic, potential = fns.energy(p, v, NOMINAL_EFF)
    spring_energy = 0.5 * spring_Nm_rad * ca.sumsqr(theta1 - theta1_0)
    rhs = ca.Function("rhs", [p, v], [ca.vertcat(v, acc)])
    energy = ca.Function("energy", [p, v], [kinetic, potential + spring_energy])
    sol = solve_ivp(lambda t, x: np.asarray(rhs(x[:3], x[3:])).ravel(), (0.0, duration_s),
                    np.concatenate([p0, v0]), method="DOP853", rtol=1e-11, atol=1e-13,
                    dense_output=False, t_eval=np.linspace(0.0, duration_s, 401))
    assert sol.success, sol.message
    kin_pot = np.array([[float(x) for x in energy(s[:3], s[3:])] for s in sol.y.T])
    return sol, kin_pot


def test_energy_conserved_without_gravity_or_input() -> None:
    """Gravity-free, unforced: T alone is conserved (to 1e-6 relative over 2 s)."""
    fns = dynamics_functions(ACRA2009, gravity_m_s2=0.0)
    p0, v0 = np.array([-0.02, -0.015, 0.115]), np.array([0.025, 0.015, 0.008])
    sol, kin_pot = _simulate(fns, p0, v0, 2.0)
    positions = sol.y[:3].T
    assert in_workspace(positions).all()           # the motion stays in the workspace
    assert np.linalg.norm(positions[-1] - p0) > 0.04  # and goes somewhere (> 4 cm)
    assert np.abs(kin_pot[:, 1]).max() == 0.0       # no potential at all
    kinetic = kin_pot[:, 0]
    assert np.abs(kinetic - kinetic[0]).max() / kinetic[0] < 1e-6
    # the speed is not constant: the configuration-dependent mass matrix trades it between axes
    speeds = np.linalg.norm(sol.y[3:], axis=0)
    assert speeds.max() / speeds.min() > 1.02


def test_energy_conserved_with_gravity_and_no_input() -> None:
    """With gravity and nothing else the device falls, so it only stays in the workspace for a
    fraction of a second: T + V is checked over that flight (thrown up from low down)."""
    fns = dynamics_functions(ACRA2009)
    p0, v0 = np.array([0.0, -0.03, 0.12]), np.array([0.05, 0.55, 0.0])
    sol, kin_pot = _simulate(fns, p0, v0, 0.09)
    assert in_workspace(sol.y[:3].T).all()
    total = kin_pot.sum(axis=1)
    # the energy is traded between T and V (relative change measured against the kinetic scale,
    # since V is only defined up to a constant)
    assert np.ptp(kin_pot[:, 0]) > 0.3 * kin_pot[0, 0]
    assert np.abs(total - total[0]).max() / kin_pot[:, 0].max() < 1e-6


def test_energy_conserved_with_gravity_over_two_seconds() -> None:
    """Gravity plus a conservative spring at the pivots (potential k/2 |theta1 - theta1_0|^2,
    included in the energy) keeps the device oscillating in the workspace for 2 s: T + V +
    V_spring is conserved to 1e-6 of the kinetic scale."""
    fns = dynamics_functions(ACRA2009)
    p0, v0 = np.array([0.005, 0.0, 0.12]), np.array([0.25, -0.2, 0.15])
    sol, kin_pot = _simulate(fns, p0, v0, 2.0, spring_Nm_rad=1.0)
    assert in_workspace(sol.y[:3].T).all()
    total = kin_pot.sum(axis=1)
    assert np.ptp(kin_pot[:, 0]) > 0.5 * kin_pot[0, 0]
    assert np.abs(total - total[0]).max() / kin_pot[:, 0].max() < 1e-6


# --- statics and inverse/forward consistency ---------------------------------------------------

def test_holding_command_is_gravity_through_the_jacobian(model: FalconModel) -> None:
    pts = sample_workspace(300, np.random.default_rng(21))
    held = model.holding_commands(pts)
    g = model.gravity(pts)
    tau = np.einsum("nji,nj->ni", np.linalg.inv(jacobian(pts)), g)       # J^-T g
    torque_per_command = -ACRA2009.drive_ratio * ACRA2009.ks_Nm            # at rest
    assert np.allclose(held, tau / torque_per_command, rtol=1e-9, atol=1e-9)
    # and with those commands the device does not accelerate
    assert np.abs(model.forward_dynamics(pts, np.zeros_like(pts), held)).max() < 1e-9
    # gravity acts along -y, so g (= dV/dp) points up: the sum of the masses times 9.81
    # bounds its y component, which is positive everywhere
    assert (g[:, 1] > 0).all()


@pytest.mark.parametrize("effects", [
    Effects(),
    Effects(coulomb_Nm=0.01, viscous_Nms=2e-3, stribeck_Nm=0.005, payload_kg=0.05,
            motor_gain=0.9, gravity_tilt_x_rad=0.1, gravity_tilt_z_rad=-0.05, kd_sign=-1.0),
    Effects(coulomb_leg0_Nm=0.004, coulomb_leg2_Nm=0.01, motor_gain_leg1=0.8, motor_gain_leg2=1.2,
            link_mass_scale=1.4, encoder_offset_rad=0.05),
], ids=["nominal", "all-smooth-effects", "per-leg-link-encoder"])
def test_inverse_then_forward_returns_the_acceleration(model: FalconModel, effects: Effects) -> None:
    rng = np.random.default_rng(22)
    pts = sample_workspace(500, rng)
    vel = rng.normal(scale=0.3, size=(500, 3))
    acc = rng.normal(scale=5.0, size=(500, 3))
    m = model.with_effects(effects)
    tc = m.inverse_dynamics(pts, vel, acc)
    assert np.allclose(m.forward_dynamics(pts, vel, tc), acc, rtol=1e-8, atol=1e-8)
    # single-point path gives the same numbers as the batch path
    assert np.allclose(m.inverse_dynamics(pts[0], vel[0], acc[0]), tc[0], rtol=1e-12)


def test_mass_matrix_symmetric_positive_definite(model: FalconModel) -> None:
    pts = sample_workspace(1000, np.random.default_rng(23))
    mass = np.asarray(model.functions.mass_matrix.map(1000)(pts.T, np.repeat(NOMINAL_EFF[:, None], 1000, 1)))
    mass = mass.T.reshape(1000, 3, 3)  # map stacks the 3x3 blocks side by side
    assert np.allclose(mass[0], model.mass_matrix(pts[0]), rtol=1e-12)
    assert np.abs(mass - np.swapaxes(mass, 1, 2)).max() < 1e-12 * np.abs(mass).max()
    eig = np.linalg.eigvalsh(mass)
    # at least the end effector's 82.73 g in every direction
    assert eig.min() > ACRA2009.effector_mass_kg


# --- a second, independent formulation ----------------------------------------------------------

@pytest.fixture(scope="module")
def states() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(24)
    return (sample_workspace(40, rng), rng.normal(scale=0.3, size=(40, 3)), rng.normal(scale=5.0, size=(40, 3)))


def test_reference_kinematics_is_independent_but_equal(states) -> None:
    pts = states[0]
    assert np.abs(ref.theta1(pts, ACRA2009) - inverse_kinematics(pts).theta1).max() < 1e-12


def test_numeric_lagrangian_agrees(model: FalconModel, states) -> None:
    """M (Hessian of T in v), h ((dM/dt) v - 1/2 d(v^T M v)/dp) and g (dV/dp), all by finite
    differences of the energies of a separate numpy model, agree to 1e-6 relative."""
    potential_offsets = []
    for p, v, a in zip(*states):
        assert _rel(ref.mass_matrix(p, ACRA2009), model.mass_matrix(p)) < 1e-6
        assert _rel(ref.bias_term(p, v, ACRA2009), model.bias(p, v)) < 1e-6
        assert _rel(ref.gravity_term(p, ACRA2009), model.gravity(p)) < 1e-6
        assert _rel(ref.inverse_dynamics(p, v, a, ACRA2009), model.inverse_dynamics(p, v, a)) < 1e-6
        kinetic, potential = model.energy(p, v)
        assert kinetic == pytest.approx(ref.kinetic_energy(p, v, ACRA2009), rel=1e-8)
        potential_offsets.append(potential - ref.potential_energy(p, ACRA2009))
    # potentials differ only by a constant (where the pivots and the effector joint sit)
    assert np.ptp(potential_offsets) < 1e-9


def test_bias_is_quadratic_in_velocity(model: FalconModel, states) -> None:
    p, v = states[0][0], states[1][0]
    assert np.allclose(model.bias(p, 2.0 * v), 4.0 * model.bias(p, v), rtol=1e-12)
    assert np.abs(model.bias(p, np.zeros(3))).max() == 0.0


def test_lumped_mass_limit() -> None:
    """With every mass and inertia but the effector's zero, M = m I and g = m 9.81 y-hat."""
    params = ref.lumped_params(ACRA2009)
    pts = sample_workspace(50, np.random.default_rng(25), params)
    for payload in (0.0, 0.2):
        m = FalconModel(params, Effects(payload_kg=payload))
        mass = ACRA2009.effector_mass_kg + payload
        for p in pts[:10]:
            assert np.allclose(m.mass_matrix(p), mass * np.eye(3), rtol=0, atol=1e-12)
        assert np.allclose(m.gravity(pts), [0.0, mass * 9.81, 0.0], rtol=0, atol=1e-12)
        assert np.abs(m.bias(pts, np.ones_like(pts))).max() < 1e-12


def test_gravity_option() -> None:
    """gravity_m_s2 is a builder argument: 0 removes gravity, it scales linearly, defaults to
    9.81 (the default call is the same cached object), and bad values are refused."""
    pts = sample_workspace(20, np.random.default_rng(26))
    default = dynamics_functions(ACRA2009)
    assert dynamics_functions(ACRA2009, DEFAULT_LIMITS, 9.81) is default
    assert FalconModel(ACRA2009).functions is default
    g_default = np.asarray(default.gravity.map(20)(pts.T, np.repeat(NOMINAL_EFF[:, None], 20, 1)))
    g_zero = np.asarray(dynamics_functions(ACRA2009, gravity_m_s2=0.0).gravity.map(20)(
        pts.T, np.repeat(NOMINAL_EFF[:, None], 20, 1)))
    g_double = np.asarray(dynamics_functions(ACRA2009, gravity_m_s2=19.62).gravity.map(20)(
        pts.T, np.repeat(NOMINAL_EFF[:, None], 20, 1)))
    assert np.abs(g_zero).max() == 0.0
    assert np.allclose(g_double, 2.0 * g_default, rtol=1e-12)
    for bad in (-1.0, float("nan"), "9.81"):
        with pytest.raises(InvalidParameterError, match="gravity_m_s2"):
            dynamics_functions(ACRA2009, gravity_m_s2=bad)


def test_new_effects_round_trip_and_validate() -> None:
    """Per-leg, link-mass and encoder effects survive JSON and are checked on construction."""
    import json
    import math

    from falcon_plan.errors import InvalidParameterError

    e = Effects(coulomb_leg1_Nm=0.01, motor_gain_leg2=0.9, link_mass_scale=1.2, encoder_offset_rad=-0.07)
    assert Effects.from_dict(json.loads(json.dumps(e.to_dict()))) == e
    params = FalconModel().params
    assert e.encoder_params(params).theta_home_rad == pytest.approx(params.theta_home_rad - 0.07)
    assert Effects().encoder_params(params) is params
    for bad in ({"coulomb_leg0_Nm": -0.1}, {"motor_gain_leg1": 0.0}, {"link_mass_scale": -1.0},
                {"encoder_offset_rad": math.pi}):
        with pytest.raises(InvalidParameterError, match=next(iter(bad))):
            Effects(**bad)


def test_per_leg_effects_act_on_their_leg_only() -> None:
    """A per-leg gain scales only that leg's command; per-leg friction adds only at that
    pivot; the link-mass scale changes the holding commands less than a payload of the same
    mass would (the legs' mass sits near the pivots)."""
    p = np.array([0.01, -0.005, 0.12])
    v = np.array([0.05, 0.02, -0.03])
    a = np.zeros(3)
    base = FalconModel().inverse_dynamics(p, v, a)
    gain = FalconModel(effects=Effects(motor_gain_leg1=0.8)).inverse_dynamics(p, v, a)
    assert gain[1] == pytest.approx(base[1] / 0.8) and gain[[0, 2]] == pytest.approx(base[[0, 2]])
    fric = FalconModel(effects=Effects(coulomb_leg2_Nm=0.01)).inverse_dynamics(p, v, a)
    assert fric[[0, 1]] == pytest.approx(base[[0, 1]]) and abs(fric[2] - base[2]) > 1.0
    hold = FalconModel().holding_commands(p)
    m_leg = FalconModel().params.leg_mass_kg
    link = FalconModel(effects=Effects(link_mass_scale=2.0)).holding_commands(p) - hold
    payload = FalconModel(effects=Effects(payload_kg=3 * m_leg)).holding_commands(p) - hold
    assert 0 < np.abs(link).max() < np.abs(payload).max()


@pytest.mark.parametrize("name", ["inverse_dynamics", "forward_dynamics", "workspace_margins", "gravity", "bias"])
def test_compiled_batches_agree_with_the_virtual_machine(model, name: str) -> None:
    """Batches and single points run compiled C (a CasADi map with common subexpressions
    eliminated, in chunks of BATCH_CHUNK or SMALL_BATCH_CHUNK points); CasADi's virtual
    machine on the Function itself gives the same numbers, inside and outside a chunk
    boundary (BATCH_CHUNK + 3 points; 9 points; one)."""
    from falcon_plan.model import dynamics
    from falcon_plan.model.workspace import sample_workspace

    rng = np.random.default_rng(11)
    n = dynamics.BATCH_CHUNK + 3
    p = sample_workspace(n, rng)
    v, a, tc = rng.normal(0, 0.3, (n, 3)), rng.normal(0, 5.0, (n, 3)), rng.normal(0, 1500, (n, 3))
    args = {"inverse_dynamics": (p, v, a), "forward_dynamics": (p, v, tc), "workspace_margins": (p,),
            "gravity": (p,), "bias": (p, v)}[name]
    model.prepare_small_batches()
    assert dynamics._compiled_batch(model.functions, name, dynamics.BATCH_CHUNK) is not None
    assert dynamics._compiled_batch(model.functions, name, dynamics.SMALL_BATCH_CHUNK) is not None
    fn, eff = getattr(model.functions, name), model.effect_vector

    def machine(rows: Any) -> np.ndarray:
        return np.array([np.asarray(fn(*[x[i] for x in args], eff)).ravel() for i in rows])

    evaluate = getattr(model, name)
    np.testing.assert_allclose(evaluate(*args)[::37], machine(range(0, n, 37)), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(evaluate(*[x[:9] for x in args]), machine(range(9)), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(evaluate(*[x[0] for x in args]), machine([0])[0], rtol=1e-12, atol=1e-12)


def test_a_single_point_never_starts_a_compilation(model) -> None:
    """Real-time loops evaluate single points (the doctor's holding commands): such a call
    runs what is already built, never the compiler (a compilation stalled the doctor's loop
    past the device's watchdog)."""
    from falcon_plan.model import dynamics

    dynamics._batch_cache.pop((id(model.functions), "leg_torques", dynamics.SMALL_BATCH_CHUNK), None)
    torques = model.leg_torques(np.array([0.0, 0.0, 0.12]), np.zeros(3), np.zeros(3))
    assert torques.shape == (3,)
    assert dynamics._compiled_batch(model.functions, "leg_torques", dynamics.SMALL_BATCH_CHUNK, build=False) is None


def test_the_mass_matrix_solve_by_its_adjugate_solves_it(model: FalconModel) -> None:
    """solve_mass (the forward dynamics' M^-1 rhs in closed form) gives x with M x = rhs, to
    rounding, at 200 workspace points and random right-hand sides (that the forward dynamics
    built with it invert the inverse dynamics, another formulation, is
    test_inverse_then_forward_returns_the_acceleration)."""
    from falcon_plan.model.symbolic import solve_mass

    m_sym, b_sym = ca.SX.sym("m", 3, 3), ca.SX.sym("b", 3)
    solve = ca.Function("solve", [m_sym, b_sym], [solve_mass(0.5 * (m_sym + m_sym.T), b_sym)])
    rng = np.random.default_rng(7)
    pts = sample_workspace(200, rng)
    for p in pts:
        mass = np.asarray(model.mass_matrix(p))
        rhs = rng.normal(size=3)
        x = np.asarray(solve(mass, rhs)).ravel()
        np.testing.assert_allclose(mass @ x, rhs, rtol=1e-10, atol=1e-12 * np.abs(rhs).max())
