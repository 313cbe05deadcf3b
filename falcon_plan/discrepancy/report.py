"""Writing a :class:`~falcon_plan.discrepancy.workflow.DiscrepancyReport` to a folder.

``report.json`` (the JSON of ``--json``), ``effects.json`` (the corrected Effects,
``Effects.to_dict()``: load it with ``Effects.from_dict``), ``report.md`` and the plots it
shows: residual against leg velocity per leg, time traces before and after (training and
held-out), the evidence of every candidate. matplotlib is imported here only (Agg backend).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


from falcon_plan.discrepancy.workflow import DiscrepancyReport


def _fmt(x: Any, digits: int = 4) -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return f"{x:.{digits}g}"


def _plots(report: DiscrepancyReport, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    arr = report.localisation.arrays
    use = arr["use"]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), sharey=True)
    for leg, ax in enumerate(axes):
        ax.plot(arr["theta1_dot"][use, leg], arr["residual_nominal"][use, leg], ".", ms=1.5,
                alpha=0.4, label="nominal")
        ax.plot(arr["theta1_dot"][use, leg], arr["residual_corrected"][use, leg], ".", ms=1.5,
                alpha=0.4, label="corrected")
        ax.set_xlabel(f"leg {leg} dtheta1/dt [rad/s]")
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("logged - inverse dynamics [command units]")
    axes[0].legend(markerscale=6)
    fig.suptitle("Inverse-dynamics residual against leg velocity (training log)")
    fig.tight_layout()
    fig.savefig(out / "residual_vs_velocity.png", dpi=90)
    plt.close(fig)
    files.append("residual_vs_velocity.png")

    # the residual's shape: against the command, the position and the time (an effect
    # outside the library shows there: a dead band acts on the command, cogging on the
    # position, a drift in time)
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8), sharey=True)
    xs = (("command", "logged command (low-passed) [command units]", 1.0),
          ("theta1", "leg angle theta1 [deg]", 180.0 / math.pi), ("t", "t [s]", 1.0))
    for ax, (key, label, scale) in zip(axes, xs):
        for leg in range(3):
            x = arr[key][use, leg] if arr[key].ndim == 2 else arr[key][use]
            ax.plot(x * scale, arr["residual_corrected"][use, leg], ".", ms=1.2, alpha=0.35, label=f"leg {leg}")
        ax.set_xlabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("logged - corrected inverse dynamics\n[command units]")
    axes[0].legend(markerscale=6, fontsize=8)
    outside = report.unexplained.outside_library
    fig.suptitle("Residual of the corrected model against command, position and time (training log)"
                 + (f"\n{outside['reason']}" if outside else ""), fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "residual_shape.png", dpi=90)
    plt.close(fig)
    files.append("residual_shape.png")

    tr = report.traces
    for tag, title in (("train", "training"), ("held", "held-out")):
        fig, axes = plt.subplots(3, 1, figsize=(12, 7), sharex=True)
        for leg, ax in enumerate(axes):
            t = tr[f"{tag}_t"]
            ax.plot(t, tr[f"{tag}_nominal"][:, leg] - tr[f"{tag}_enc"][:, leg], lw=0.8, label="nominal - log")
            ax.plot(t, tr[f"{tag}_corrected"][:, leg] - tr[f"{tag}_enc"][:, leg], lw=0.8, label="corrected - log")
            ax.set_ylabel(f"leg {leg} [counts]")
            ax.grid(True, alpha=0.3)
        axes[0].legend()
        axes[-1].set_xlabel("t [s]")
        fig.suptitle(f"Closed-loop replay error, {title} log, before and after")
        fig.tight_layout()
        fig.savefig(out / f"replay_{tag}.png", dpi=90)
        plt.close(fig)
        files.append(f"replay_{tag}.png")

    plot_evidence(report.evidence, report.settings["threshold_delta_bic"], out / "evidence.png")
    files.append("evidence.png")
    return files


def plot_evidence(evidence: list[dict[str, Any]], threshold: float, path: Path) -> Any:
    """PNG at ``path``: each candidate's evidence alone (the ``evidence`` rows of a
    DiscrepancyReport: ``effect``, ``delta_bic_alone``, ``status``) as bars on a signed log
    scale labelled in dBIC, with the selection ``threshold`` (a dBIC). Returns the Figure
    (closed to pyplot)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in evidence if r["delta_bic_alone"] is not None]
    fig, ax = plt.subplots(figsize=(11, 4.2))
    names = [r["effect"] for r in rows]
    vals = [r["delta_bic_alone"] for r in rows]

    def signed_log(v: float) -> float:  # the bars' scale: log10(1 + |dBIC|) with dBIC's sign
        return math.copysign(math.log10(1 + abs(v)), v)

    ax.barh(names, [signed_log(v) for v in vals],
            color=["tab:green" if r["status"] == "selected" else "tab:gray" for r in rows])
    ax.axvline(signed_log(threshold), color="r", ls="--", label=f"threshold: dBIC {threshold:g} (very strong evidence)")
    ax.axvline(0.0, color="0.3", lw=0.8)
    # ticks labelled in dBIC itself, not in its logarithm
    top = max([abs(v) for v in vals] + [threshold])
    powers = [10.0 ** k for k in range(0, int(math.ceil(math.log10(1 + top))) + 1)]
    lowest = min([0.0, *(signed_log(v) for v in vals)]) - 0.5
    ticks = sorted({0.0, *powers, *(-p for p in powers if signed_log(-p) >= lowest)})
    ax.set_xticks([signed_log(v) for v in ticks], [f"{v:g}" for v in ticks])
    ax.set_xlabel("dBIC of each candidate alone: BIC of the base model minus BIC with the effect added\n"
                  "(log scale both ways; > 0 the data favour the effect, < 0 they favour leaving it out)")
    ax.set_title("Evidence for each candidate effect alone", fontsize=11)
    from matplotlib.patches import Patch

    handles = [Patch(color="tab:green", label="selected"), Patch(color="tab:gray", label="not selected")]
    # beside the bars, not over them (placed "best" it covered the longest ones)
    ax.legend(handles=[*handles, *ax.get_legend_handles_labels()[0]], fontsize=8, loc="upper left",
              bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return fig


def _markdown(report: DiscrepancyReport, plots: list[str]) -> str:
    d = report.to_dict()
    lines = ["# Model discrepancy report", ""]
    lines += [f"**Effects found:** {', '.join(report.effects)}", ""]
    if report.indistinguishable:
        lines += ["**Indistinguishable on this data** (delta BIC between them below the threshold; "
                  "the first of each group is used in the corrected model):"]
        lines += [f"- {' / '.join(g)}" for g in report.indistinguishable]
        lines += [""]
    u = report.unexplained
    if u.unexplained and u.where is not None:
        w, when, outside = u.where, u.when, u.outside_library
        lines += [f"**Unexplained remainder:** the corrected model replays the training log with "
                  f"{u.replay_rms_counts:.2f} counts RMS (floor from this log: {u.floor_counts:.2f} counts; "
                  f"both from t = {u.judged['judged_from_s']:.2f} s, the motion's start, on"
                  + (f", without {u.judged['stall_windows_s']:.2f} s after {u.judged['host_stalls']} host stall(s)"
                     if u.judged["stall_windows_s"] else "") + "); "
                  f"it sits mostly on the {w.leg_name} leg (leg {w.leg}) during '{w.phase}' "
                  f"({w.rms_counts:.2f} counts RMS there)"
                  f", and most between t = {when.start_s:.1f} and {when.end_s:.1f} s"
                  + ". " + (f"Outside the library: {outside['reason']}. " if outside else "")
                  + ("No candidate in the library explains it." if report.effects == ["none"] else
                     "It remains after the named effects; no further candidate explains it.")
                  + " See residual_shape.png (residual against command, position and time).", ""]
    lines += ["## Fitted parameters", "", "| effect | parameter | value | std | unit |", "|---|---|---|---|---|"]
    for fld, p in report.parameters.items():
        lines.append(f"| {p.effect} | {fld} | {_fmt(p.value)} | {_fmt(p.std, 2)} | {p.unit} |")
    lines += ["", f"Corrected effects (`effects.json`): `{json.dumps(report.corrected.to_dict())}`", ""]
    hb, ha = report.heldout_before, report.heldout_after
    lines += ["## Held-out check (closed-loop tracking replay)", "",
              "| | leg 0 | leg 1 | leg 2 | all |", "|---|---|---|---|---|",
              f"| nominal [counts] | {' | '.join(_fmt(x, 3) for x in hb.rms_counts)} | {_fmt(hb.rms_counts_all, 3)} |",
              f"| corrected [counts] | {' | '.join(_fmt(x, 3) for x in ha.rms_counts)} | {_fmt(ha.rms_counts_all, 3)} |",
              f"| nominal [mm] | {' | '.join(_fmt(x, 3) for x in hb.rms_mm)} | {_fmt(hb.rms_mm_all, 3)} |",
              f"| corrected [mm] | {' | '.join(_fmt(x, 3) for x in ha.rms_mm)} | {_fmt(ha.rms_mm_all, 3)} |", ""]
    lines += ["## Evidence (training log only)", "",
              f"Selection rule: {report.settings['selection_rule']}", "",
              "| effect | criterion | dBIC alone | dBIC given final | fitted alone | status |",
              "|---|---|---|---|---|---|"]
    for r in report.evidence:
        fitted = ", ".join(f"{k}={_fmt(v, 3)}" for k, v in r["fitted_alone"].items())
        status = r["status"] + (f" (indistinguishable from {', '.join(r['indistinguishable_from'])})"
                                if r.get("indistinguishable_from") else "")
        lines.append(f"| {r['effect']} | {r['criterion']} | {_fmt(r['delta_bic_alone'], 4)} | "
                     f"{_fmt(r['delta_bic_given_final'], 4)} | {fitted} | {status} |")
    loc = d["locate_train"]
    lines += ["", "## Where the nominal model disagrees (training log)", "",
              "Inverse-dynamics residual RMS [command units] per leg: nominal "
              f"{[round(x, 1) for x in loc['rms_per_leg_nominal']]}, corrected "
              f"{[round(x, 1) for x in loc['rms_per_leg_corrected']]}.", "",
              "| phase | leg 0 | leg 1 | leg 2 |", "|---|---|---|---|"]
    for ph, row in loc["rms_per_phase_nominal"].items():
        lines.append(f"| {ph} | {' | '.join(_fmt(x, 3) for x in row)} |")
    lines += ["", "| band | leg 0 | leg 1 | leg 2 |", "|---|---|---|---|"]
    for band, row in loc["band_rms_nominal"].items():
        lines.append(f"| {band} | {' | '.join(_fmt(x, 3) for x in row)} |")
    lines += ["", f"Residual RMS against assumed extra delay 0..6 samples: "
              f"{[round(x, 1) for x in loc['rms_vs_extra_delay']]} (best {loc['best_extra_delay']}); "
              f"peak cross-correlation lag of residual vs command rate per leg: {loc['xcorr_lag_samples']} samples.",
              "", "Open-loop replay over 80 ms windows from the measured state, RMS error at the window end "
              f"[counts]: nominal {[round(x, 1) for x in loc['window_end_rms_counts_nominal']]}, corrected "
              f"{[round(x, 1) for x in loc['window_end_rms_counts_corrected']]}.", ""]
    lines += ["## Plots", ""] + [f"![{p}]({p})" for p in plots]
    lines += ["", "## Settings and timings", "", "```", json.dumps(d["settings"], indent=1),
              json.dumps(d["timings_s"], indent=1), "```", ""]
    return "\n".join(lines)


def write_report(report: DiscrepancyReport, out_dir: str | Path, plots: bool = True) -> dict[str, Path]:
    """Write report.json, effects.json, report.md and the plots into ``out_dir`` (created)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "report.json", "effects": out / "effects.json", "markdown": out / "report.md"}
    paths["json"].write_text(json.dumps(report.to_dict(), indent=1) + "\n")
    paths["effects"].write_text(json.dumps(report.corrected.to_dict(), indent=1) + "\n")
    files = _plots(report, out) if plots else []
    paths["markdown"].write_text(_markdown(report, files))
    return paths
