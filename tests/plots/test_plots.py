"""The plots of plans and runs: written as PNGs, and the numbers they draw checked against an
independent computation (the workspace check, the executor's own tracking measure)."""
from __future__ import annotations

import json

import numpy as np
import pytest

import falcon_plan as fp
from falcon_plan.cli import main
from falcon_plan.execution.device_factory import open_device
from falcon_plan.execution.executor import Executor
from falcon_plan.model.workspace import check_workspace, sample_workspace
from falcon_plan.plots.plan import workspace_margins_deg
from falcon_plan.plots.run import run_errors

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _is_png(path) -> bool:
    return path.read_bytes()[:8] == PNG_MAGIC and path.stat().st_mode & 0o777 == 0o644


@pytest.fixture(scope="module")
def planned(model):
    return fp.plan((0.0, 0.0, 0.12), (0.03, 0.02, 0.14), fp.PlanOptions.fast(), model)


def test_margins_agree_with_the_workspace_check(model, rng) -> None:
    """Inside the workspace every margin is >= 0; beyond a leg-angle limit the leg margin is
    negative, by as much as the angle is past the limit (checked from the angles directly)."""
    inside = sample_workspace(500, rng, model.params, model.limits)
    margins = workspace_margins_deg(inside, model)
    assert all((values >= -1e-9).all() for values in margins.values())
    box = rng.uniform((-0.09, -0.09, 0.04), (0.09, 0.09, 0.2), size=(4000, 3))
    check = check_workspace(box, model.params, model.limits)
    past_leg_limit = check.reachable & ~check.within_leg_range
    leg = workspace_margins_deg(box[past_leg_limit], model)["leg angle [deg]"]
    theta1 = np.degrees(check.angles.theta1[past_leg_limit])
    beyond = np.maximum(-20.0 - theta1, theta1 - 80.0).max(axis=1)
    assert past_leg_limit.sum() > 50 and np.allclose(leg, -beyond)


def test_plan_plot(planned, model, tmp_path) -> None:
    path = fp.plot_plan(planned.trajectory, tmp_path / "plan.png", model=model, tc_max=2500)
    assert path == tmp_path / "plan.png" and _is_png(path)


def test_run_errors_match_the_executors_measure_and_plot(planned, model, tmp_path) -> None:
    """The run plot's errors (batch forward kinematics of measured and reference counts)
    equal the executor's tracking report (online FK of the counts against the plan)."""
    log_path = tmp_path / "run.csv"
    with open_device("sim", rate_hz=800.0, model=model, start_m=(0.0, 0.0, 0.12)) as device:
        device.home()
        report = Executor(device, model, 800.0, log_path, preroll_s=0.3).run(planned.trajectory)
    log = fp.read_log(log_path)
    counts, mm = run_errors(log)
    moving = log.t_s - log.t_s[0] >= 0.3 - 1e-9  # the executor measures from the end of the pre-roll
    rms = lambda a: np.sqrt(np.mean(a ** 2, axis=0))  # noqa: E731
    assert np.allclose(rms(counts[moving]), report.tracking.counts_rms)
    assert rms(np.linalg.norm(mm[moving], axis=1)) == pytest.approx(report.tracking.norm_rms_mm, abs=1e-4)
    assert _is_png(fp.plot_run(log, tmp_path / "run.png"))


def test_a_log_without_reference_cannot_be_plotted(tmp_path) -> None:
    log = fp.FalconLog([0.0, 0.1], [[0, 0, 0]] * 2, [[0, 0, 0]] * 2)
    with pytest.raises(fp.LogFormatError, match="reference columns"):
        fp.plot_run(log, tmp_path / "x.png")


@pytest.mark.slow
def test_plan_and_execute_draw_next_to_their_outputs(tmp_path, capsys) -> None:
    out = tmp_path / "move.json"
    assert main(["plan", "--from", "0,0,0.12", "--to", "0.02,0.01,0.13", "--fast", "--out", str(out)]) == 0
    assert _is_png(tmp_path / "move.png") and out.stat().st_mode & 0o777 == 0o644
    log = tmp_path / "run.csv"
    assert main(["execute", "--device", "sim", "--trajectory", str(out), "--from", "0,0,0.12",
                 "--log", str(log)]) == 0
    assert _is_png(tmp_path / "run.png")
    capsys.readouterr()
    assert main(["execute", "--device", "sim", "--from", "0,0,0.12", "--to", "0.01,0,0.125",
                 "--planner", "quintic", "--plot", str(tmp_path / "only.png")]) == 0
    text = capsys.readouterr().out
    assert _is_png(tmp_path / "only.png") and "plot: " in text and "log: " not in text  # no log was asked for


def test_run_title_is_words_and_the_gains_plot_is_written(model, planned, tmp_path) -> None:
    """The run plot's title names the controller in words (not its metadata string); the gain
    plot of the plan's LQR schedule is a PNG, and the schedule's gains are those it draws."""
    from falcon_plan.plots.run import run_title

    log_path = tmp_path / "run.csv"
    with open_device("sim", rate_hz=800.0, model=model, start_m=(0.0, 0.0, 0.12)) as device:
        device.home()
        Executor(device, model, 800.0, log_path, preroll_s=0.2).run(planned.trajectory)
    title = run_title(fp.read_log(log_path))
    assert "time-varying LQR" in title and "e_pos=" not in title and "simulated device" in title
    schedule = fp.Controller.executor_default(800.0, model).schedule_along(planned.trajectory, model)
    assert schedule.gains_at().shape == (schedule.samples, 3, 12)
    assert _is_png(fp.plot_gains(schedule, tmp_path / "gains.png"))


@pytest.mark.parametrize("limit", ["constant", "device"])
def test_the_plan_plot_draws_the_bound_the_report_measures(model, limit) -> None:
    """The plot's command bound is the plan's (tc_max minus the feedback reserve, or L(w)
    minus it), the one the report's "max |Tc|/bound" uses: the plot's peak over it agrees
    with the report's to 0.1 %, and it is not the bare tc_max (2500) the plot used to draw."""
    from falcon_plan.plots.plan import PLOT_RATE_HZ, plan_bound

    result = fp.plan((0.0, 0.0, 0.12), (0.03, 0.02, 0.14), fp.PlanOptions.fast(limit=limit), model)
    report, trajectory = result.report, result.trajectory
    bound = plan_bound(trajectory, model)
    assert bound.describe() == report.command_bound and bound.reserve == 150.0
    dense = trajectory.sample(PLOT_RATE_HZ, model)
    allowed = bound.allowed(model, dense.position_m, dense.velocity_m_s, dense.acceleration_m_s2)
    used = float((np.abs(dense.commands) / allowed).max())
    assert abs(used - report.worst_command_ratio) < 1e-3
    if limit == "constant":
        assert bound.at_rest == 2350.0 and np.abs(dense.commands).max() / 2500.0 < 0.95


def test_the_report_names_the_nearest_workspace_limit_in_degrees(planned, model) -> None:
    """The report's nearest workspace limit is the smallest angle margin along the plan, in
    degrees, as the plot draws it (computed here from the plot's own margins), and names
    which margin and leg (the planner's rows mix radians and sines: their smallest was another)."""
    from falcon_plan.model.workspace import ANGLE_MARGIN_NAMES, angle_margins_deg

    report = planned.report
    dense = planned.trajectory.sample(4000.0, model)
    margins = workspace_margins_deg(dense.position_m, model)
    margins.pop("forward singularity")
    name, values = min(margins.items(), key=lambda kv: np.nanmin(kv[1]))
    assert report.worst_angle_margin_deg == pytest.approx(np.nanmin(values), abs=0.05)
    assert report.worst_angle_margin_name.startswith(name.removesuffix(" [deg]"))
    per_leg, _ = angle_margins_deg(dense.position_m, model)
    leg = int(np.nanargmin(per_leg[:, ANGLE_MARGIN_NAMES.index(name.removesuffix(" [deg]")), :]) % 3)
    assert report.worst_angle_margin_name.endswith(f"leg {leg}")
    assert f"nearest workspace limit {report.worst_angle_margin_deg:.1f} deg away" in report.summary()


def _fake_batch(tmp_path):
    """A batch of 6 solved problems (solve times 0.3 ms..600 ms across the methods) and 2
    refused ones, as the runner writes its rows."""
    from falcon_plan.batch.runner import METHODS, PLANNER, BatchResult, ResultRow, RunOptions

    rows = []
    for i in range(8):
        for k, method in enumerate(METHODS):
            if i >= 6:
                rows.append(ResultRow(f"refuse_{i}", method, "refused:goal_outside",
                                      "refused" if method == PLANNER else "skipped", reason="goal_outside"))
            else:
                rows.append(ResultRow(f"move_{i}", method, "solved", "solved", duration_s=0.1 + 0.01 * i,
                                      duration_ratio=1.0 + 0.1 * k, solve_time_s=0.0003 * 10 ** k * (1 + i)))
    return BatchResult(rows, RunOptions(), 1.0)


def _drawn_labels(fig, axis) -> list[str]:
    """The tick labels ``axis`` shows inside its view once ``fig`` is drawn."""
    fig.canvas.draw()
    lo, hi = sorted(axis.axes.get_ylim() if axis is axis.axes.yaxis else axis.axes.get_xlim())
    return [t.get_text() for t, v in zip(axis.get_ticklabels(), axis.get_ticklocs()) if lo <= v <= hi and t.get_text()]


def test_bench_plots_show_refusals_and_label_every_decade(tmp_path) -> None:
    """The durations plot lists refused problems too, with the planner's outcome (its title
    says x marks what did not run); the solve-time plot labels its log axis across the whole
    range, not only up to 10 ms."""
    from falcon_plan.batch.summary import plot_durations, plot_solve_times

    result = _fake_batch(tmp_path)
    durations = plot_durations(result, tmp_path / "durations.png")
    ax = durations.axes[0]
    assert {"refuse_6", "refuse_7"} <= {t.get_text() for t in ax.get_yticklabels()}
    assert sum("planner: refused (goal_outside)" == t.get_text() for t in ax.texts) == 2
    solve = plot_solve_times(result, tmp_path / "solve_times.png")
    labels = _drawn_labels(solve, solve.axes[0].yaxis)
    numbers = sorted(float(t) for t in labels)
    assert numbers[0] < 1.0 and numbers[-1] >= 100.0 and len([v for v in numbers if v > 10.0]) >= 3
    assert _is_png(tmp_path / "durations.png") and _is_png(tmp_path / "solve_times.png")


def test_the_evidence_plot_fits_its_title_and_says_what_its_axis_is(tmp_path) -> None:
    from falcon_plan.discrepancy.report import plot_evidence

    values = {"coulomb_friction": 195.0, "motor_gain": 630.0, "kd_sign": -6.2, "command_delay": -32.0,
              "viscous_friction": 3.0}
    evidence = [{"effect": k, "delta_bic_alone": v, "status": "selected" if v > 100 else "rejected"}
                for k, v in values.items()]
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = plot_evidence(evidence, 10.0, tmp_path / "evidence.png")
    ax = fig.axes[0]
    canvas = FigureCanvasAgg(fig)  # pyplot has closed it: a canvas to measure the text on
    canvas.draw()
    renderer = canvas.get_renderer()
    for text in (ax.title, ax.xaxis.label):
        box = text.get_window_extent(renderer)
        assert box.x0 >= 0 and box.x1 <= fig.bbox.x1, f"cut off: {text.get_text()!r}"
    assert "BIC of the base model minus BIC with the effect added" in ax.get_xlabel()
    assert {"-10", "0", "10", "100"} <= set(_drawn_labels(fig, ax.xaxis))  # dBIC itself, not its log
    assert _is_png(tmp_path / "evidence.png")


def test_the_evidence_plots_legend_hides_no_bar(tmp_path) -> None:
    """The legend sits where it covers none of the bars (with a calibration's 14 candidates,
    'best' put it over two of them)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from falcon_plan.discrepancy.report import plot_evidence

    values = {"coulomb_friction": 201.6, "viscous_friction": 77.9, "stribeck_friction": 165.0,
              "command_delay": -23.2, "backlash": -24.4, "cable_compliance": -26.2, "payload_mass": 576.6,
              "motor_gain": 616.5, "gravity_tilt": -12.8, "kd_sign": -6.2, "leg_friction": 189.7,
              "leg_motor_gain": 606.8, "encoder_offset": 413.7, "link_mass": 565.7}
    evidence = [{"effect": k, "delta_bic_alone": v, "status": "selected" if k in ("coulomb_friction", "motor_gain")
                 else "rejected"} for k, v in values.items()]
    fig = plot_evidence(evidence, 10.0, tmp_path / "evidence.png")
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    ax = fig.axes[0]
    legend = (ax.get_legend() or fig.legends[0]).get_window_extent(renderer)
    bars = [patch.get_window_extent(renderer) for patch in ax.patches]
    assert len(bars) == len(values)
    hidden = [name for name, bar in zip(values, bars) if bar.width > 0 and legend.overlaps(bar)]
    assert not hidden, f"the legend covers the bars of {hidden}"
    assert legend.x1 <= fig.bbox.x1 and legend.y0 >= 0, "the legend is cut off"


def test_characterise_views_of_one_quantity_share_one_unclipped_scale(rng) -> None:
    """The isometric view and the slices of one quantity use one colour range covering both
    (the slices were clipped to the sampled points' range), each view with its colour bar;
    the workspace figure keeps z for the points and the margin for the slices."""
    from falcon_plan.plots.characterise import _figure

    points = rng.uniform(-0.05, 0.05, size=(200, 3)) + (0, 0, 0.12)
    values = rng.uniform(1.0, 2.0, size=200)
    a, b = np.linspace(-0.05, 0.05, 5), np.linspace(0.08, 0.16, 4)
    grid = np.full((4, 5), 0.5)
    grid[0, 0], grid[1, 1] = 3.0, np.nan
    slices = [("xz", 0.0, "side", a, b, grid), ("xy", 0.12, "back", a, b, grid)]
    fig = _figure(points, values, slices, "t", ("q", "q"), separate_scale=False)
    iso_scatter = fig.axes[0].collections[0]
    meshes = [ax.collections[0] for ax in fig.axes[1:] if ax.collections and hasattr(ax.collections[0], "get_array")
              and ax.get_label() != "<colorbar>"]
    assert iso_scatter.get_clim() == (0.5, 3.0) and all(m.get_clim() == (0.5, 3.0) for m in meshes)
    assert sum(ax.get_label() == "<colorbar>" for ax in fig.axes) == 2
    workspace = _figure(points, 1e3 * points[:, 2], slices, "t", ("z [mm]", "margin [deg]"), separate_scale=True)
    assert workspace.axes[0].collections[0].get_clim() == (1e3 * points[:, 2].min(), 1e3 * points[:, 2].max())


def test_request_goal_plot_draws_the_executed_run_beside_the_plan(model, capsys, tmp_path) -> None:
    """A real service on loopback runs a goal on its simulated device: the goal result carries
    the run (its falcon log in short), ``request goal --plot FILE.png`` draws that run (measured
    against the plan) and the plan next to it as FILE-plan.png; the run's tracking error
    agrees with the executor's report."""
    from service.client import FalconClient, wait_for_instance
    from service.config import SessionSettings, free_loopback_port
    from service.device import RUN_MAX_SAMPLES, make_runner, run_log
    from service.handlers import falcon_planner
    from service.keys import ServiceKeys
    from service.server import FalconService

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    keys = ServiceKeys(prefix="plots")
    service = FalconService(SessionSettings.server([endpoint]), keys, falcon_planner, make_runner("sim", model))
    with service, FalconClient(SessionSettings.client([endpoint]), prefix="plots") as client:
        wait_for_instance(client, keys.instance)
        base = ["request", "--prefix", "plots", "--connect", endpoint]
        plot = tmp_path / "goal.png"
        assert main([*base, "goal", "g1", "--to", "0.02,0.01,0.13", "--plot", str(plot), "--json"]) == 0
        result = json.loads(capsys.readouterr().out)
    assert result["status"] == "done" and _is_png(plot) and _is_png(tmp_path / "goal-plan.png")
    run = result["run"]
    assert result["tracking_report"]["log_path"] is None  # the service's log was temporary
    log = run_log(run)
    assert len(log.t_s) <= RUN_MAX_SAMPLES and len(log.t_s) * run["every"] >= result["tracking_report"]["samples"]
    _, error_mm = run_errors(log)
    moving = log.t_s - log.t_s[0] >= float(log.meta["motion_start_s"]) - 1e-9  # the report's rows
    reported = result["tracking_report"]["tracking"]["norm_max_mm"]
    assert np.linalg.norm(error_mm[moving], axis=1).max() == pytest.approx(reported, rel=0.3, abs=0.05)
