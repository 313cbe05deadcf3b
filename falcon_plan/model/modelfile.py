"""The model file: a corrected (or any) Falcon model as JSON, with where it came from.

What the discrepancy workflow finds is written here, and ``plan``, ``execute``, ``simulate``,
``bench``, ``experiment``, ``serve`` and ``calibrate`` load it with ``--model FILE``; from
Python, :func:`load_model` (``fp.load_model``; written by :func:`save_model`). Layout (one JSON object)::

    {"format": "falcon-plan model", "version": 1,
     "params": {...FalconParams.to_dict()...},       # the whole parameter set
     "effects": {...Effects.to_dict()...},            # only the effects that are on
     "provenance": {"created_utc": "...", "source": "...", "logs": {...},
                    "effects_named": [...], "parameters": {field: {value, std, unit, effect}},
                    "heldout_rms_counts": {"nominal": x, "corrected": y}, ...}}

Effects and parameters are written through their own ``to_dict`` so that fields added to them
later carry over. The workspace limits are the project's defaults (not part of the file).
Writing is atomic (temporary file, then rename); reading names the file and the problem.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from falcon_plan.errors import InvalidParameterError
from falcon_plan.fileio import write_text
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import COULOMB_SMOOTHING_RAD_S, Effects
from falcon_plan.model.params import FalconParams

log = logging.getLogger(__name__)

FORMAT = "falcon-plan model"
VERSION = 1


@dataclass(frozen=True)
class ModelFile:
    """A model with its provenance (free-form JSON-ready dict)."""

    model: FalconModel
    provenance: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The file's JSON object."""
        return {"format": FORMAT, "version": VERSION, "params": self.model.params.to_dict(),
                "effects": self.model.effects.to_dict(), "provenance": _json_ready(self.provenance)}

    def summary(self) -> dict[str, Any]:
        """A short JSON-ready description (what the service's ``info`` reports)."""
        prov = self.provenance
        return {"params": self.model.params.name, "effects": self.model.effects.to_dict(),
                "nominal": self.model.effects.is_nominal,
                "created_utc": prov.get("created_utc"), "source": prov.get("source"),
                "path": prov.get("path")}


def _json_ready(value: Any) -> Any:
    """Non-finite floats as strings ("inf", "nan"), containers recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    return value


def save_model(path: str | os.PathLike[str], model: FalconModel,
               provenance: dict[str, Any] | None = None) -> Path:
    """Write ``model`` (+ provenance; ``created_utc`` added if absent) to ``path`` atomically,
    mode 0644 (:func:`falcon_plan.fileio.write_text`); OutputError if it cannot be written."""
    prov = dict(provenance or {})
    prov.setdefault("created_utc", datetime.now(timezone.utc).isoformat(timespec="seconds"))
    text = json.dumps(ModelFile(model, prov).to_dict(), indent=2) + "\n"
    return write_text(path, text, "the model file")


def read_model_file(path: str | os.PathLike[str]) -> ModelFile:
    """Read a model file; InvalidParameterError naming the file and the problem. The
    provenance gets ``path`` (the file read)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InvalidParameterError(f"cannot read the model file {path}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise InvalidParameterError(f"the model file {path} is not JSON: {exc}") from None
    except UnicodeDecodeError as exc:
        raise InvalidParameterError(f"the model file {path} is not JSON text: byte {exc.start} is not UTF-8 "
                                    "(`falcon-plan discrepancy --out DIR` writes a model file)") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InvalidParameterError(f"{path} is not a falcon-plan model file (expected \"format\": "
                                    f"\"{FORMAT}\"; `falcon-plan discrepancy --out DIR` writes one)")
    if data.get("version") != VERSION:
        raise InvalidParameterError(f"{path}: model file version {data.get('version')!r} is not "
                                    f"supported (this reader knows {VERSION})")
    try:
        params = FalconParams.from_dict(data.get("params", {}))
        effects = Effects.from_dict(data.get("effects", {}))
    except (InvalidParameterError, TypeError) as exc:
        raise InvalidParameterError(f"{path}: {exc}") from None
    missing = sorted({f.name for f in dataclasses.fields(FalconParams)} - {"notes"} - set(data.get("params", {})))
    if missing:   # (older files lack parameters added since: those keep working)
        log.warning("%s: parameter(s) %s not given: the paper's values (acra2009) are used for them", path,
                    ", ".join(missing))
    provenance = dict(data.get("provenance") or {})
    provenance["path"] = str(path)
    return ModelFile(FalconModel(params, effects), provenance)


def load_model(path: str | os.PathLike[str] | None) -> FalconModel:
    """The model in the model file at ``path``; the nominal model (acra2009, no effects) for
    None."""
    return FalconModel() if path is None else read_model_file(path).model



def unplannable_effect_notes(effects: Effects, params: FalconParams | None = None) -> list[str]:
    """One line per effect of ``effects`` that cannot enter the planner's dynamics (the
    plant-only ones: command delay, backlash, cable compliance; and a friction smoothing
    sharper than the planner takes, :func:`planning_effects`), saying what is done instead;
    with ``params`` the backlash note also gives the slop in encoder counts."""
    notes = []
    if effects.extra_delay_samples:
        notes.append(f"command delay (+{effects.extra_delay_samples} samples) cannot enter the planner's "
                     "dynamics; instead the executor's feed-forward leads by that many more samples")
    if effects.backlash_rad > 0:
        counts = "" if params is None else f", up to ~{0.5 * effects.backlash_rad * params.counts_per_rad:.0f} counts"
        notes.append(f"backlash ({effects.backlash_rad:.4g} rad) cannot enter the planner (not smooth); "
                     f"the plan assumes a rigid drive and the executor's PD takes up the slop{counts} "
                     "at reversals")
    if math.isfinite(effects.cable_stiffness_Nm_rad):
        notes.append(f"cable compliance ({effects.cable_stiffness_Nm_rad:.4g} N.m/rad) cannot enter the "
                     "planner; the plan assumes a rigid drive and the executor's PD corrects the cable stretch")
    if planning_effects(effects) != effects:
        notes.append(f"friction smoothing {effects.friction_smoothing_rad_s:.3g} rad/s is sharper than the "
                     f"planner takes (a near-discontinuous sign upsets its optimiser): the plan uses "
                     f"{COULOMB_SMOOTHING_RAD_S:g} rad/s; the executor's feed-forward uses the fitted value")
    return notes


def planning_effects(effects: Effects) -> Effects:
    """``effects`` as the planner's dynamics take them: the friction smoothing speed no
    sharper than the default :data:`~falcon_plan.model.effects.COULOMB_SMOOTHING_RAD_S` [rad/s]
    (the rest unchanged; :func:`unplannable_effect_notes` says when this changed anything)."""
    if effects.friction_smoothing_rad_s >= COULOMB_SMOOTHING_RAD_S:
        return effects
    return effects.replace(friction_smoothing_rad_s=COULOMB_SMOOTHING_RAD_S)


__all__ = ["ModelFile", "save_model", "read_model_file", "load_model", "unplannable_effect_notes", "planning_effects",
           "FORMAT", "VERSION"]
