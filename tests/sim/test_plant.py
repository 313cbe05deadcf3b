"""SimPlant: timing (delay, hold), quantisation, clamping, the saturation rule, the PD step,
the batched paths and the plant-only effects."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import angles_to_counts, counts_to_position, position_to_counts
from falcon_plan.control import EncoderPD
from falcon_plan.model.saturation import SATURATION_RELEASE_SPEED_RAD_S
from falcon_plan.sim.equations import END_STOP_MARGIN_RAD
from falcon_plan.sim.plant import SimPlant

START_M = (0.0, 0.0, 0.125)


@pytest.fixture(scope="module")
def plant(model: FalconModel) -> SimPlant:
    return SimPlant(model)


def _hold(plant: SimPlant, seconds: float, ref: np.ndarray | None = None) -> np.ndarray:
    """Run the PD at a fixed reference (default: the counts now); return the last command."""
    pd = EncoderPD(plant.rate_hz)
    ref = plant.counts.astype(float) if ref is None else ref
    run = plant.run_pd(pd, np.tile(ref, (int(round(seconds * plant.rate_hz)), 1)))
    return run.commands[-1]


def test_counts_are_whole_and_match_the_motor_angle(plant: SimPlant) -> None:
    plant.reset(START_M)
    for _ in range(30):
        counts = plant.step([300, -200, 100])
        assert counts.dtype == np.int64 and counts.shape == (3,)
        exact = angles_to_counts(plant.motor_angle_rad, plant.model.params)
        assert np.array_equal(counts, np.floor(exact + 0.5).astype(np.int64))
    assert plant.time_s == pytest.approx(30 / 800.0)


def test_home_reads_zero_counts(plant: SimPlant) -> None:
    plant.reset()
    assert plant.counts.tolist() == [0, 0, 0]


@pytest.mark.parametrize("extra", [0, 1])
def test_command_acts_exactly_2_plus_extra_periods_later(model: FalconModel, extra: int) -> None:
    """Two plants from the same state; one gets a command step at call 0. Their states are
    bit-identical until the command starts acting, then they differ."""
    effects = Effects(extra_delay_samples=extra)
    quiet, kicked = SimPlant(model, effects=effects), SimPlant(model, effects=effects)
    for p in (quiet, kicked):
        p.reset(START_M)
    delay = 2 + extra
    for k in range(delay + 2):
        quiet.step(None)
        kicked.step([2000, -2000, 1000] if k == 0 else None)
        same = np.array_equal(quiet.velocity_m_s, kicked.velocity_m_s)
        assert same == (k < delay), f"period {k}"


def test_positive_command_drives_counts_down(plant: SimPlant) -> None:
    plant.reset(START_M)
    free = plant.run_open_loop(np.full((12, 3), np.nan))[-1]
    plant.reset(START_M)
    pushed = plant.run_open_loop(np.tile([1500.0, 0.0, 0.0], (12, 1)))[-1]
    assert pushed[0] < free[0] - 5


def test_commands_are_rounded_and_clamped(plant: SimPlant) -> None:
    plant.reset(START_M)
    a = plant.run_open_loop(np.tile([9000.0, -9000.0, 1.4], (6, 1)))
    plant.reset(START_M)
    b = plant.run_open_loop(np.tile([4096.0, -4096.0, 1.0], (6, 1)))
    assert np.array_equal(a, b)
    with pytest.raises(InvalidParameterError):
        plant.step([np.nan, 0, 0])
    with pytest.raises(InvalidParameterError):
        plant.step([1, 2])


def test_static_saturation_rule(model: FalconModel) -> None:
    plant = SimPlant(model)
    plant.reset(START_M)
    for _ in range(3):
        plant.step([4000, -3000, 2000])
    # first acting period: the legs have only the speed gravity gave them in 2 periods
    motor = plant.motor_commands
    assert 2500 <= motor[0] < 2600 and -2600 < motor[1] <= -2500 and motor[2] == 2000
    for _ in range(40):
        plant.step([4000, -3000, 2000])
    assert plant.motor_commands.tolist() == [4000, -3000, 2000]  # in motion: lifted
    unsaturated = SimPlant(model, saturation=False)
    unsaturated.reset(START_M)
    for _ in range(3):
        unsaturated.step([4000, -3000, 2000])
    assert unsaturated.motor_commands.tolist() == [4000, -3000, 2000]


def test_saturation_blends_smoothly_with_speed(plant: SimPlant) -> None:
    """L(w) = 2500 + 1596 s(|w| / w_r), s the smoothstep: 2500 at rest, 3298 at w_r / 2."""
    p = np.asarray(START_M)
    jac = np.asarray(plant.model.functions.jacobian(p, plant._eff))
    limits = []
    for fraction in (0.0, 0.25, 0.5, 1.0, 2.0):
        w = np.full(3, fraction * SATURATION_RELEASE_SPEED_RAD_S)
        x = np.concatenate([p, np.linalg.solve(jac, w)])
        limits.append(float(np.asarray(plant.functions.motor_command(x, [4096.0] * 3, plant._eff,
                                                                     plant._pp)).ravel()[0]))
    u = np.array([0.0, 0.25, 0.5, 1.0, 1.0])
    assert limits == pytest.approx(2500 + 1596 * u * u * (3 - 2 * u), abs=1e-6)
    assert np.all(np.diff(limits) >= 0)


@pytest.mark.parametrize("rate_hz, hold", [(800.0, 80), (1000.0, 100)])
def test_force_drops_100ms_after_the_last_command(model: FalconModel, rate_hz: float, hold: int) -> None:
    plant = SimPlant(model, rate_hz=rate_hz)
    plant.reset(START_M)
    active = []
    plant.step([100, 200, 300])
    for _ in range(2 + hold + 3):
        plant.step(None)
        active.append(plant.acting_commands.tolist())
    # acting from period 2 (the delay) for `hold` periods, then zero
    assert active[0] == [0, 0, 0]
    assert all(a == [100, 200, 300] for a in active[1:1 + hold])
    assert all(a == [0, 0, 0] for a in active[1 + hold:])


def test_step_none_before_any_command_means_no_force(plant: SimPlant) -> None:
    plant.reset(START_M)
    plant.step(None)
    assert plant.acting_commands.tolist() == [0, 0, 0]


def test_pd_steady_state_error_is_holding_command_over_kp(plant: SimPlant) -> None:
    """Integral-free PD: at rest kp (n - ref) = Tc cancels gravity, so n - ref = Tc_hold / kp."""
    goal = np.array([0.02, -0.01, 0.13])
    ref = position_to_counts(goal, plant.model.params)
    plant.reset(START_M)
    pd = EncoderPD(plant.rate_hz)
    run = plant.run_pd(pd, np.tile(ref, (1200, 1)))
    n, tc = run.counts[-1], run.commands[-1]
    assert np.abs(run.counts[-50:] - n).max() <= 1  # settled
    assert np.abs((n - ref) - tc / pd.kp).max() <= 0.1  # Tc = round(kp (n - ref)), v = 0
    hold = plant.model.holding_commands(plant.position_m)
    assert np.abs(tc - hold).max() <= pd.kp * 1.0  # within one count of quantisation
    assert np.abs(n - ref - hold / pd.kp).max() <= 1.0


def test_run_pd_equals_the_step_loop(model: FalconModel) -> None:
    ref = np.zeros((500, 3))
    ref[50:] = position_to_counts([0.02, 0.015, 0.14], model.params)
    ff = np.zeros((500, 3))
    ff[100:200] = [50.0, -30.0, 10.0]
    looped, batched = SimPlant(model), SimPlant(model)
    for p in (looped, batched):
        p.reset(START_M)
        p.step([700, -300, 100])  # something pending in the delay line
    pd = EncoderPD(800.0)
    counts, cmds, n = [], [], looped.counts
    for k in range(500):
        tc = pd.update(n, ref[k], ff[k])
        counts.append(n)
        cmds.append(tc)
        n = looped.step(tc)
    pd2 = EncoderPD(800.0)
    run = batched.run_pd(pd2, ref, ff)
    assert np.array_equal(run.counts, np.array(counts)) and np.array_equal(run.commands, np.array(cmds))
    assert np.array_equal(batched.position_m, looped.position_m)
    # the filtered velocity to the last bits: the batched loop's law is compiled for this
    # machine (fused multiply-adds, batch.FLAGS), the Python loop's rounds every product
    np.testing.assert_allclose(pd2.velocity_counts_s, pd.velocity_counts_s, rtol=1e-12, atol=0.0)
    assert run.t_s[1] - run.t_s[0] == pytest.approx(1 / 800.0) and batched.time_s == looped.time_s
    # the delay line and the firmware carry on identically (queued commands, then the hold)
    for _ in range(5):
        assert np.array_equal(batched.step(None), looped.step(None))
        assert np.array_equal(batched.acting_commands, looped.acting_commands)


def test_run_open_loop_equals_the_step_loop(model: FalconModel) -> None:
    plant = SimPlant(model)
    rng = np.random.default_rng(7)
    cmds = model.holding_commands(np.asarray(START_M)) + rng.integers(-300, 300, (450, 3))
    cmds[200:300] = np.nan  # no commands: the hold, then the force drops
    plant.reset(START_M)
    a = plant.run_open_loop(cmds)
    x_batch = plant.position_m
    plant.reset(START_M)
    b = np.array([plant.step(None if np.isnan(c).all() else c) for c in cmds])
    assert np.array_equal(a, b) and np.array_equal(plant.position_m, x_batch)


def test_unheld_device_comes_to_rest_on_its_end_stops(plant: SimPlant) -> None:
    """With no force the device droops under gravity until legs reach their mechanical stops
    (END_STOP_MARGIN_RAD beyond the leg-angle limits), as the real one does; it stays
    reachable, so its encoders keep reading and forward kinematics keeps working."""
    plant.reset(START_M)
    counts = plant.run_open_loop(np.full((1600, 3), np.nan))
    limits = plant.model.limits
    low, high = limits.theta1_min_rad - END_STOP_MARGIN_RAD, limits.theta1_max_rad + END_STOP_MARGIN_RAD
    theta = plant.theta1_rad
    assert np.all(np.isfinite(plant.position_m)) and plant.position_m[1] < START_M[1] - 0.05
    on_stop = (np.abs(theta - low) < np.radians(1.0)) | (np.abs(theta - high) < np.radians(1.0))
    assert on_stop.sum() >= 2, np.degrees(theta)
    assert np.all(theta > low - np.radians(1.0)) and np.all(theta < high + np.radians(1.0))
    # the reading at the stops converts back to the true position within quantisation
    assert np.linalg.norm(counts_to_position(counts[-1]) - plant.position_m) < 1e-4


# --- plant-only effects ------------------------------------------------------------------------

def _settle(model: FalconModel, effects: Effects, seconds: float = 1.0) -> SimPlant:
    plant = SimPlant(model, effects=effects, compile=False)
    plant.reset(START_M)
    _hold(plant, seconds, ref=position_to_counts(np.asarray(START_M), model.params))
    return plant


@pytest.fixture(scope="module")
def rigid_held(model: FalconModel) -> SimPlant:
    return _settle(model, Effects())


def test_cable_compliance_deflects_the_leg_by_torque_over_stiffness(model: FalconModel,
                                                                   rigid_held: SimPlant) -> None:
    """Encoders are on the motors: under a gravity load the leg lags the motor by tau / k."""
    k = 300.0
    plant = _settle(model, Effects(cable_stiffness_Nm_rad=k))
    twist = plant.theta1_rad - plant.motor_angle_rad
    p = plant.position_m
    tau_hold = np.asarray(model.functions.leg_torques(p, np.zeros(3), np.zeros(3), model.effect_vector)).ravel()
    # leg_torques is the torque the legs need; the cable supplies it: k (q_m - theta1) = tau
    assert twist == pytest.approx(-tau_hold / k, rel=0.05, abs=2e-6)
    assert np.abs(twist).max() > 1e-4  # a real deflection, not numerical noise
    # the encoder still settles where the rigid plant's does (same static balance)
    assert np.abs(plant.counts - rigid_held.counts).max() <= 2


def test_stiff_cable_converges_to_the_rigid_plant(model: FalconModel) -> None:
    ref = np.tile(position_to_counts([0.015, 0.01, 0.135], model.params), (240, 1))
    runs = []
    for effects in (Effects(), Effects(cable_stiffness_Nm_rad=2.0e4)):
        plant = SimPlant(model, effects=effects, compile=False)
        plant.reset(START_M)
        runs.append(plant.run_pd(EncoderPD(800.0), ref).counts)
    assert np.abs(runs[0] - runs[1]).max() <= 2


def test_backlash_lets_the_leg_sag_by_half_the_slop(model: FalconModel, rigid_held: SimPlant) -> None:
    slop = 0.004  # rad of leg angle, about 6 counts
    plant = _settle(model, Effects(backlash_rad=slop))
    gap = plant.theta1_rad - plant.motor_angle_rad
    rigid_gap = -np.asarray(model.functions.leg_torques(plant.position_m, np.zeros(3), np.zeros(3),
                                                        model.effect_vector)).ravel()
    # gravity takes up the slop on its side: half the band, plus the contact spring's stretch
    assert np.sign(gap).tolist() == np.sign(rigid_gap).tolist()
    assert np.abs(gap) == pytest.approx(slop / 2, rel=0.1)


def test_extra_delay_rings_more(model: FalconModel) -> None:
    """A longer command delay erodes the PD's phase margin: a larger overshoot."""
    goal = position_to_counts([0.02, 0.0, 0.135], model.params)
    overshoot = []
    for extra in (0, 3):
        plant = SimPlant(model, effects=Effects(extra_delay_samples=extra))
        plant.reset(START_M)
        start = plant.counts.astype(float)
        pd, n, counts = EncoderPD(800.0), plant.counts, []
        for _ in range(800):  # the per-step API (run_pd would compile a delay line per delay)
            n = plant.step(pd.update(n, goal))
            counts.append(n)
        direction = np.sign(goal - start)
        overshoot.append(float(np.max((np.array(counts) - counts[-1]) * direction)))
    assert overshoot[1] > overshoot[0]


def test_viscous_friction_damps_the_step(model: FalconModel) -> None:
    goal = position_to_counts([0.02, 0.0, 0.135], model.params)
    peaks = []
    for effects in (Effects(), Effects(viscous_Nms=0.02)):
        plant = SimPlant(model, effects=effects)
        plant.reset(START_M)
        run = plant.run_pd(EncoderPD(800.0), np.tile(goal, (800, 1)))
        peaks.append(float(np.abs(np.diff(run.counts, axis=0)).max()))
    assert peaks[1] < peaks[0]


def test_bad_arguments(model: FalconModel) -> None:
    with pytest.raises(InvalidParameterError):
        SimPlant(model, rate_hz=0.0)
    with pytest.raises(InvalidParameterError):
        SimPlant(model, substeps=0)
    plant = SimPlant(model)
    with pytest.raises(InvalidParameterError):
        plant.reset([0.0, 0.0])
    with pytest.raises(InvalidParameterError):
        plant.run_pd(EncoderPD(1000.0), np.zeros((3, 3)))
    with pytest.raises(InvalidParameterError):
        plant.run_open_loop(np.zeros((3, 2)))


def test_run_pd_in_pieces_equals_one_run(model: FalconModel) -> None:
    """Runs shorter than the delay line, and across chunk boundaries, join seamlessly."""
    ref = np.tile(position_to_counts([0.01, 0.02, 0.13], model.params), (460, 1))
    whole, pieces = SimPlant(model), SimPlant(model)
    for p in (whole, pieces):
        p.reset(START_M)
    expected = whole.run_pd(EncoderPD(800.0), ref)
    pd, parts, start = EncoderPD(800.0), [], 0
    for size in (1, 1, 237, 221):
        parts.append(pieces.run_pd(pd, ref[start:start + size]))
        start += size
    assert np.array_equal(np.vstack([r.counts for r in parts]), expected.counts)
    assert np.array_equal(np.vstack([r.commands for r in parts]), expected.commands)
    assert np.array_equal(np.concatenate([r.t_s for r in parts]), expected.t_s)
    assert np.array_equal(pieces.position_m, whole.position_m)


@pytest.mark.parametrize("compliant", [False, True])
def test_every_chunk_computes_the_same_merged_or_not(model: FalconModel, compliant: bool) -> None:
    """A compiled chunk's library is named by the unmerged Function and compiled from the merged
    one (common subexpressions shared): both, evaluated by CasADi, give the same numbers over a
    chunk of a moving plant (the timed PD chunk with ticks, late readings and held commands)."""
    from falcon_plan.sim.batch import BATCH_CHUNK, KINDS, TIMED_LINE, plant_function
    from falcon_plan.sim.equations import PlantLayout

    layout = PlantLayout(model.params, model.limits, compliant, 2)
    effects = Effects(coulomb_Nm=0.004, payload_kg=0.03, **({"backlash_rad": 0.01} if compliant else {}))
    plant = SimPlant(model, effects=effects, substeps=2, compile=False)
    plant.reset(np.array(START_M))
    rng = np.random.default_rng(3)
    for kind in KINDS:
        merged, unmerged = (plant_function(layout, kind, 2, merged=m) for m in (True, False))
        args = []
        for i in range(merged.n_in()):
            shape = merged.size_in(i)
            name = merged.name_in(i)
            if name == "eff":
                args.append(effects.smooth_vector())
            elif name == "pp":
                args.append(plant._pp)
            elif name in ("x", "x0", "z0"):
                z = np.zeros(shape[0])
                z[:layout.n_states] = plant._x
                args.append(z)
            elif name == "tick":
                args.append(np.vstack([rng.random(BATCH_CHUNK) < 0.9, np.full(BATCH_CHUNK, 1000.0),
                                       rng.random(BATCH_CHUNK), rng.random(BATCH_CHUNK) < 0.95]))
            elif name == "w":
                w = np.zeros((TIMED_LINE, BATCH_CHUNK))
                w[2] = 0.7
                w[3] = 0.3
                args.append(w)
            elif name == "gains":
                args.append(np.array([10.0, 0.1, 0.27, 1000.0, 4096.0][:shape[0]]))
            else:   # commands, references, feed-forward
                args.append(rng.uniform(-300.0, 300.0, shape))
        a, b = merged(*args), unmerged(*args)
        for x, y in zip(a if isinstance(a, (list, tuple)) else [a], b if isinstance(b, (list, tuple)) else [b]):
            x, y = np.asarray(x), np.asarray(y)
            assert np.isfinite(x).all(), kind
            np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-9, err_msg=kind)


def test_a_plant_loaded_by_its_recipe_runs_as_one_built_afresh(model: FalconModel, monkeypatch) -> None:
    """A process loads a plant's compiled chunk by the recipe a build recorded (no symbolics):
    a PD run through it reads the same counts as through the chunk built and keyed afresh."""
    from falcon_plan.compiled import build
    from falcon_plan.sim import batch

    effects = Effects(coulomb_Nm=0.004, payload_kg=0.02)

    def run() -> np.ndarray:
        plant = SimPlant(model, effects=effects)
        plant.reset(np.array(START_M))
        ref = np.tile(plant.counts + 40.0, (600, 1))
        return plant.run_pd(EncoderPD(plant.rate_hz), ref).counts

    loaded = run()
    plant = SimPlant(model, effects=effects)
    if plant.compiled:
        recipe = batch.recipe_file("falcon_plant_pd", batch.LIBRARY_SOURCES, plant.layout, "pd",
                                   plant.delay_samples, batch.FLAGS)
        assert build.recorded_recipe(recipe, 1, 1) is not None
    batch._library.cache_clear()
    monkeypatch.setattr(build, "recorded_recipe", lambda recipe, libraries, names=0: None)
    try:
        fresh = run()
    finally:
        batch._library.cache_clear()
    assert np.abs(loaded - loaded[0]).max() > 10       # it moved
    np.testing.assert_array_equal(loaded, fresh)
