"""What a recording holds: its topics, their JSON Schemas and the messages made from falcon-log rows.

Every message is JSON (message encoding ``json``, schema encoding ``jsonschema``), so Foxglove,
PlotJuggler and a few lines of Python read it. Times are in the run's own clock: a row's log
time is its falcon-log ``t`` [s] (slot k at k / rate from the first tick), and every message
also carries ``t_s``. Units are in the field names (``_m``, ``_mm``, ``_rad``, ``_rad_s``;
counts and commands are the device's integers, commands in command units of +-4096).

Topics (see :data:`TOPICS`); the first five (six with timing columns) get one message per
falcon-log row, and the reader rebuilds the FalconLog from legs, commands, reference and
timing:

==========================  ======================  =========================================
topic                       schema                  what, when
==========================  ======================  =========================================
/falcon/legs                falcon_plan.Legs        encoder counts, leg angles, leg speeds
/falcon/commands            falcon_plan.Commands    commands sent, the controller's clamp, the
                                                    device's speed-dependent limit L(w)
/falcon/reference           falcon_plan.Reference   the planned counts and leg angles
/falcon/end_effector        falcon_plan.EndEffector measured (forward kinematics of the counts)
                                                    and planned position [m, base frame]
/falcon/tracking_error      falcon_plan.Tracking    measured minus planned, counts and mm
/falcon/timing              falcon_plan.Timing      the log's further columns (per-tick timing)
/tf                         foxglove.FrameTransform world -> falcon_base -> end_effector
                                                    (and end_effector_planned), at VIEW_RATE_HZ
/falcon/scene               foxglove.SceneUpdate    the legs, base and end effector in 3D
/falcon/plan                falcon_plan.Plan        the trajectory and the planner's report
/falcon/plan/path           foxglove.PosesInFrame   the planned path in 3D
/falcon/run                 falcon_plan.RunReport   the executor's report (tracking, timing)
/falcon/goal                falcon_plan.GoalEvent   a service goal's events
==========================  ======================  =========================================

The frame ``falcon_base`` is the device's base frame (MODEL-CONVENTIONS: x right, y up, z
toward the user); ``world`` is z up (Foxglove's default view), turned +90 deg about x from it.
The 3D legs are drawn as the model's lumped geometry: pivot -> knee -> end-effector joint.
"""
from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.falconlog import parse_controller
from falcon_plan.model.kinematics import scalar_leg_frames
from falcon_plan.model.params import FalconParams
from falcon_plan.model.saturation import SaturationModel

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel

VIEW_RATE_HZ = 50.0
"""Rate of the 3D messages (/tf, /falcon/scene) in a recording, and of the live view's
batches [Hz] (at most 60)."""
BASE_FRAME = "falcon_base"
WORLD_FRAME = "world"

LEGS_TOPIC = "/falcon/legs"
REFERENCE_TOPIC = "/falcon/reference"
COMMANDS_TOPIC = "/falcon/commands"
END_EFFECTOR_TOPIC = "/falcon/end_effector"
TRACKING_TOPIC = "/falcon/tracking_error"
TF_TOPIC = "/tf"
SCENE_TOPIC = "/falcon/scene"
PLAN_TOPIC = "/falcon/plan"
PLAN_PATH_TOPIC = "/falcon/plan/path"
TIMING_TOPIC = "/falcon/timing"
RUN_TOPIC = "/falcon/run"
GOAL_TOPIC = "/falcon/goal"

LOG_META_NAME = "falcon_log"
"""Name of the MCAP metadata record holding the falcon log's metadata (``# key: value``)."""


# --- JSON Schemas ------------------------------------------------------------------------------

def _num(description: str) -> dict[str, Any]:
    return {"type": "number", "description": description}


def _triple(kind: str, description: str) -> dict[str, Any]:
    return {"type": "array", "items": {"type": kind}, "minItems": 3, "maxItems": 3,
            "description": description + " (legs 0, 1, 2)"}


def _object(title: str, description: str, properties: dict[str, Any],
            required: list[str] | None = None, **extra: Any) -> dict[str, Any]:
    return {"title": title, "description": description, "type": "object", "properties": properties,
            "required": list(properties) if required is None else required, **extra}


_T_S = _num("the falcon log's time t of the row [s] (slot k at k / rate)")
_XYZ = {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"},
                                         "z": {"type": "number"}}, "required": ["x", "y", "z"]}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}, "required": list("xyzw")}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                          "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
         "required": ["sec", "nsec"]}
_COLOR = {"type": "object", "properties": {k: {"type": "number", "minimum": 0, "maximum": 1} for k in "rgba"},
          "required": list("rgba")}
_POSE = {"type": "object", "properties": {"position": _XYZ, "orientation": _QUAT},
         "required": ["position", "orientation"]}


def _xyz(description: str, nullable: bool = False) -> dict[str, Any]:
    if nullable:
        return {"description": description + " (null where forward kinematics failed)",
                "oneOf": [_XYZ, {"type": "null"}]}
    return {**_XYZ, "description": description}


SCHEMAS: dict[str, dict[str, Any]] = {s["title"]: s for s in (
    _object("falcon_plan.Timing", "The falcon log's further integer columns of the row, under their column "
            "names (e.g. per-tick timing: when the command was handed to the driver and when the reading "
            "arrived [us, host monotonic clock], slots skipped before the row).",
            {"t_s": _T_S}, additionalProperties={"type": "integer"}),
    _object("falcon_plan.Legs", "The legs as measured: encoder counts, the driven leg angle theta1 and its "
            "rate (difference of successive rows).",
            {"t_s": _T_S, "counts": _triple("integer", "encoder counts [counts]"),
             "angle_rad": _triple("number", "leg angle theta1 from the base plane toward +z [rad]"),
             "speed_rad_s": _triple("number", "leg speed d theta1/dt [rad/s]")}),
    _object("falcon_plan.Reference", "The plan in leg space: the counts and leg angles the loop follows.",
            {"t_s": _T_S, "counts": _triple("number", "planned encoder counts [counts]"),
             "angle_rad": _triple("number", "planned leg angle theta1 [rad]")}),
    _object("falcon_plan.Commands", "The commands sent and the limits they meet.",
            {"t_s": _T_S, "command": _triple("integer", "motor command sent [command units]"),
             "limit": {"type": "integer", "description": "the controller's clamp [command units]"},
             "device_limit": _triple("number", "the device's speed-dependent limit L(w) at the measured leg "
                                               "speed [command units] (2500 at rest, up to 4096)"),
             "saturated": {"type": "array", "items": {"type": "boolean"}, "minItems": 3, "maxItems": 3,
                           "description": "|command| at or over the device limit (legs 0, 1, 2)"}}),
    _object("falcon_plan.EndEffector", "End-effector position, base frame (x right, y up, z toward the user).",
            {"t_s": _T_S, "measured_m": _xyz("forward kinematics of the counts [m]", nullable=True),
             "planned_m": _xyz("forward kinematics of the planned counts [m]", nullable=True)},
            required=["t_s", "measured_m"]),
    _object("falcon_plan.Tracking", "Tracking error, measured minus planned.",
            {"t_s": _T_S, "counts": _triple("number", "per leg [counts]"),
             "position_mm": _xyz("Cartesian, base frame [mm]", nullable=True),
             "norm_mm": {"type": ["number", "null"], "description": "Euclidean norm [mm]"}}),
    _object("falcon_plan.Plan", "The trajectory a run follows (falcon_plan.trajectory.Trajectory JSON) and the "
            "planner's report (null for a saved trajectory).",
            {"trajectory": {"type": "object"}, "report": {"type": ["object", "null"]},
             "duration_s": _num("motion time [s]")}, required=["trajectory"]),
    _object("falcon_plan.RunReport", "The executor's report of the run (ExecutionReport.to_dict(): status, "
            "samples, tracking error in counts and mm, missed deadlines, jitter in us).",
            {"status": {"type": "string"}}, required=["status"], additionalProperties=True),
    _object("falcon_plan.GoalEvent", "An event of a service goal: started, planned, finished (with its final status; "
            "a goal spliced into a running one starts and plans in that goal's recording).",
            {"goal_id": {"type": "string"}, "event": {"type": "string"}, "status": {"type": "string"},
             "detail": {"type": "object"}}, required=["goal_id", "event"]),
    _object("foxglove.FrameTransform", "A transform between two frames (Foxglove well-known schema).",
            {"timestamp": _TIME, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
             "translation": {**_XYZ, "description": "[m]"}, "rotation": _QUAT}),
    _object("foxglove.PosesInFrame", "An array of timestamped poses in a frame (Foxglove well-known schema).",
            {"timestamp": _TIME, "frame_id": {"type": "string"}, "poses": {"type": "array", "items": _POSE}}),
    _object("foxglove.SceneUpdate", "Entities of a 3D scene (Foxglove well-known schema; the primitives used "
            "here: lines and spheres).",
            {"deletions": {"type": "array", "items": {"type": "object"}},
             "entities": {"type": "array", "items": _object(
                 "foxglove.SceneEntity", "A visual element in a 3D scene.",
                 {"timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
                  "lifetime": _TIME, "frame_locked": {"type": "boolean"},
                  "metadata": {"type": "array", "items": {"type": "object"}},
                  "arrows": {"type": "array"}, "cubes": {"type": "array"}, "cylinders": {"type": "array"},
                  "triangles": {"type": "array"}, "texts": {"type": "array"}, "models": {"type": "array"},
                  "spheres": {"type": "array", "items": {"type": "object", "properties": {
                      "pose": _POSE, "size": _XYZ, "color": _COLOR}}},
                  "lines": {"type": "array", "items": {"type": "object", "properties": {
                      "type": {"type": "integer", "description": "0 strip, 1 loop, 2 list"},
                      "pose": _POSE, "thickness": {"type": "number"}, "scale_invariant": {"type": "boolean"},
                      "points": {"type": "array", "items": _XYZ}, "color": _COLOR,
                      "colors": {"type": "array"}, "indices": {"type": "array"}}}}})}}),
)}
"""JSON Schema of every schema name a recording uses (title = schema name)."""

TOPICS: dict[str, str] = {
    TIMING_TOPIC: "falcon_plan.Timing", LEGS_TOPIC: "falcon_plan.Legs", REFERENCE_TOPIC: "falcon_plan.Reference",
    COMMANDS_TOPIC: "falcon_plan.Commands", END_EFFECTOR_TOPIC: "falcon_plan.EndEffector",
    TRACKING_TOPIC: "falcon_plan.Tracking", TF_TOPIC: "foxglove.FrameTransform",
    SCENE_TOPIC: "foxglove.SceneUpdate", PLAN_TOPIC: "falcon_plan.Plan", PLAN_PATH_TOPIC: "foxglove.PosesInFrame",
    RUN_TOPIC: "falcon_plan.RunReport", GOAL_TOPIC: "falcon_plan.GoalEvent"}
"""Schema name of every topic."""


def schema_bytes(name: str) -> bytes:
    """The JSON Schema of schema ``name`` (a :data:`SCHEMAS` key) as UTF-8 bytes."""
    return json.dumps(SCHEMAS[name], separators=(",", ":")).encode("utf-8")


def command_limit_of(meta: dict[str, str], params: FalconParams) -> int:
    """The controller's clamp [command units]: the ``limit=`` word of the log's ``controller``
    metadata (``meta``), else the device's range (``params.command_limit``)."""
    try:
        return int(parse_controller(meta["controller"]).gains["limit"])
    except (KeyError, ValueError):
        return int(params.command_limit)


def encoder_params_of(meta: dict[str, str]) -> FalconParams:
    """The parameter set a falcon log's metadata ``meta`` names (``params``, default acra2009) with the
    encoder home angle its feed-forward model used (``feedforward_effects``' encoder offset):
    what turns its counts into angles and positions."""
    from falcon_plan.errors import InvalidParameterError
    from falcon_plan.model.effects import Effects
    from falcon_plan.model.params import ACRA2009, get_params

    try:
        params = get_params(meta.get("params", ACRA2009.name))
    except (InvalidParameterError, OSError, ValueError):
        params = ACRA2009
    try:
        effects = Effects.from_dict(json.loads(meta.get("feedforward_effects", "{}")))
    except (ValueError, TypeError):
        return params
    return effects.encoder_params(params)


def model_metadata(model: FalconModel) -> dict[str, str]:
    """The ``model`` metadata record of a recording: parameter set and effects (JSON)."""
    return {"params": model.params.name, "effects": json.dumps(model.effects.to_dict(), sort_keys=True)}


# --- messages ---------------------------------------------------------------------------------

Message = tuple[str, float, bytes]
"""(topic, log time [s, the run's clock], JSON payload)."""


def dumps(body: Any) -> bytes:
    """``body`` as compact JSON bytes (NaN and infinities refused)."""
    return json.dumps(body, separators=(",", ":"), allow_nan=False).encode("utf-8")


def stamp(t_s: float) -> dict[str, int]:
    """A Foxglove time {sec, nsec} of ``t_s`` [s] (>= 0)."""
    ns = int(round(max(0.0, t_s) * 1e9))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _point(p: Any) -> tuple[float, float, float] | None:
    """``p`` (3 numbers [m]) as floats; None when it is None or not finite."""
    if p is None:
        return None
    x, y, z = float(p[0]), float(p[1]), float(p[2])
    return (x, y, z) if math.isfinite(x + y + z) else None


def _vec_json(p: tuple[float, ...] | None, scale: float = 1.0) -> str:
    if p is None:
        return "null"
    return '{"x":%r,"y":%r,"z":%r}' % (p[0] * scale, p[1] * scale, p[2] * scale)


_IDENTITY = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
_WORLD_FROM_BASE = {"x": math.sqrt(0.5), "y": 0.0, "z": 0.0, "w": math.sqrt(0.5)}  # +90 deg about x: y up -> z up
_GREY = {"r": 0.55, "g": 0.58, "b": 0.62, "a": 1.0}
_BLUE = {"r": 0.15, "g": 0.45, "b": 0.9, "a": 1.0}
_ORANGE = {"r": 1.0, "g": 0.55, "b": 0.1, "a": 0.6}
_GREEN = {"r": 0.2, "g": 0.75, "b": 0.35, "a": 0.9}


class RowEncoder:
    """Turns falcon-log rows into the recording's messages, one row at a time, in order.

    Parameters
    ----------
    params : the device's parameter set, with the encoder home angle the run used (a model's
        ``effects.encoder_params(params)``): counts -> angles -> positions.
    command_limit : the controller's clamp [command units].
    view_rate_hz : rate of the 3D messages [Hz].
    """

    def __init__(self, params: FalconParams, command_limit: float, view_rate_hz: float = VIEW_RATE_HZ) -> None:
        self.params = params
        self.command_limit = int(command_limit)
        self.view_period_s = 1.0 / view_rate_hz
        self._per_rad = params.counts_per_rad
        self._home = params.theta_home_rad
        self._saturation = SaturationModel.of(params)
        self._frames = scalar_leg_frames(params)
        self._prev: tuple[float, tuple[int, int, int]] | None = None
        self._next_view_s = -math.inf

    def view_due(self, t_s: float) -> bool:
        """True when the row at ``t_s`` [s] gets the 3D messages (one row per 1/VIEW_RATE_HZ)."""
        return float(t_s) >= self._next_view_s

    def skip(self, t_s: float, enc: Any) -> None:
        """Note the row at ``t_s`` [s] with counts ``enc`` without making its messages (the
        next row's leg speed still differences from it; its 3D messages are not due before)."""
        self._prev = (float(t_s), (int(enc[0]), int(enc[1]), int(enc[2])))

    def encode(self, t_s: float, enc: Any, tc: Any, ref: Any = None, measured_m: Any = None,
               planned_m: Any = None, extra: dict[str, int] | None = None) -> list[Message]:
        """The messages of one row: time ``t_s`` [s], counts ``enc`` (3), commands ``tc`` (3)
        [command units], planned counts ``ref`` (3, or None), the measured and planned
        end-effector positions ``measured_m``, ``planned_m`` [m, base frame] (forward kinematics
        of ``enc`` and ``ref``; None where unknown) and ``extra`` columns (name -> whole
        number, e.g. per-tick timing; on /falcon/timing)."""
        t = float(t_s)
        n = (int(enc[0]), int(enc[1]), int(enc[2]))
        c = (int(tc[0]), int(tc[1]), int(tc[2]))
        home, per_rad = self._home, self._per_rad
        angles = [home + x / per_rad for x in n]
        if self._prev is None or t <= self._prev[0]:
            speed = [0.0, 0.0, 0.0]
        else:
            dt = t - self._prev[0]
            speed = [(a - b) / per_rad / dt for a, b in zip(n, self._prev[1])]
        self._prev = (t, n)
        device_limit = [float(x) for x in self._saturation.limit(np.asarray(speed))]
        measured = _point(measured_m)
        planned = _point(planned_m)
        ts = repr(t)
        out: list[Message] = [
            (LEGS_TOPIC, t, ('{"t_s":%s,"counts":[%d,%d,%d],"angle_rad":[%r,%r,%r],"speed_rad_s":[%r,%r,%r]}'
                             % (ts, *n, *angles, *speed)).encode()),
            (COMMANDS_TOPIC, t, ('{"t_s":%s,"command":[%d,%d,%d],"limit":%d,"device_limit":[%r,%r,%r],'
                                 '"saturated":[%s,%s,%s]}'
                                 % (ts, *c, self.command_limit, *device_limit,
                                    *("true" if abs(ci) >= li else "false" for ci, li in zip(c, device_limit)))
                                 ).encode())]
        if ref is not None:
            r = (float(ref[0]), float(ref[1]), float(ref[2]))
            out.append((REFERENCE_TOPIC, t, ('{"t_s":%s,"counts":[%r,%r,%r],"angle_rad":[%r,%r,%r]}'
                                             % (ts, *r, *(home + x / per_rad for x in r))).encode()))
            err = None if measured is None or planned is None else tuple(m - p for m, p in zip(measured, planned))
            norm = "null" if err is None else repr(1e3 * math.sqrt(sum(e * e for e in err)))
            out.append((TRACKING_TOPIC, t, ('{"t_s":%s,"counts":[%r,%r,%r],"position_mm":%s,"norm_mm":%s}'
                                            % (ts, *(a - b for a, b in zip(n, r)), _vec_json(err, 1e3), norm)
                                            ).encode()))
        out.append((END_EFFECTOR_TOPIC, t, ('{"t_s":%s,"measured_m":%s,"planned_m":%s}'
                                            % (ts, _vec_json(measured), _vec_json(planned))).encode()))
        if extra:
            out.append((TIMING_TOPIC, t, ('{"t_s":%s,%s}' % (ts, ",".join('"%s":%d' % (k, int(v))
                                                                          for k, v in extra.items()))).encode()))
        if self.view_due(t):
            self._next_view_s = t + self.view_period_s
            out += self.view(t, angles, measured, planned)
        return out

    def view(self, t: float, angles: list[float], measured: tuple[float, float, float] | None,
             planned: tuple[float, float, float] | None) -> list[Message]:
        """The 3D messages at time ``t`` [s]: /tf (world -> base -> end effector, measured and
        planned) and the scene (legs at leg angles ``angles`` [rad], end-effector spheres)."""
        when = stamp(t)
        out: list[Message] = [(TF_TOPIC, t, dumps(transform(when, WORLD_FRAME, BASE_FRAME, (0.0, 0.0, 0.0),
                                                            _WORLD_FROM_BASE)))]
        for child, p in (("end_effector", measured), ("end_effector_planned", planned)):
            if p is not None:
                out.append((TF_TOPIC, t, dumps(transform(when, BASE_FRAME, child, p, _IDENTITY))))
        out.append((SCENE_TOPIC, t, dumps(self.scene(when, angles, measured, planned))))
        return out

    def scene(self, when: dict[str, int], angles: list[float], measured: tuple[float, float, float] | None,
              planned: tuple[float, float, float] | None) -> dict[str, Any]:
        """A SceneUpdate: the base triangle through the leg pivots, each leg pivot -> knee ->
        end effector (measured, or the knee alone when it is unknown), spheres at the measured
        (blue) and planned (orange) end effector."""
        params = self.params
        pivots, knees = [], []
        for (erx, ery, _, _), th in zip(self._frames, angles):
            radius = params.radial_offset_m
            pivots.append({"x": erx * radius, "y": ery * radius, "z": 0.0})
            reach = radius + params.a_m * math.cos(th)
            knees.append({"x": erx * reach, "y": ery * reach, "z": params.a_m * math.sin(th)})
        leg_points: list[dict[str, float]] = []
        for pivot, knee in zip(pivots, knees):
            leg_points += [pivot, knee]
            if measured is not None:
                leg_points += [knee, {"x": measured[0], "y": measured[1], "z": measured[2]}]
        entities = [
            _entity(when, "base", lines=[_line(1, pivots, _GREY, 0.004)]),
            _entity(when, "legs", lines=[_line(2, leg_points, _GREEN, 0.003)]),
        ]
        spheres = []
        for p, color, size in ((measured, _BLUE, 0.008), (planned, _ORANGE, 0.010)):
            if p is not None:
                spheres.append({"pose": {"position": {"x": p[0], "y": p[1], "z": p[2]}, "orientation": _IDENTITY},
                                "size": {"x": size, "y": size, "z": size}, "color": color})
        entities.append(_entity(when, "end_effector", spheres=spheres))
        return {"deletions": [], "entities": entities}


def transform(when: dict[str, int], parent: str, child: str, translation: Any,
              rotation: dict[str, float]) -> dict[str, Any]:
    """A foxglove.FrameTransform body: ``child`` in ``parent`` at ``translation`` [m] turned by
    ``rotation`` (quaternion x, y, z, w), at time ``when`` ({sec, nsec})."""
    return {"timestamp": when, "parent_frame_id": parent, "child_frame_id": child,
            "translation": {"x": float(translation[0]), "y": float(translation[1]), "z": float(translation[2])},
            "rotation": rotation}


def _line(kind: int, points: list[dict[str, float]], color: dict[str, float], thickness_m: float) -> dict[str, Any]:
    return {"type": kind, "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": _IDENTITY},
            "thickness": thickness_m, "scale_invariant": False, "points": points, "color": color,
            "colors": [], "indices": []}


def _entity(when: dict[str, int], entity_id: str, *, lines: list[Any] = (), spheres: list[Any] = ()) -> dict[str, Any]:
    return {"timestamp": when, "frame_id": BASE_FRAME, "id": entity_id, "lifetime": {"sec": 0, "nsec": 0},
            "frame_locked": False, "metadata": [], "arrows": [], "cubes": [], "spheres": list(spheres),
            "cylinders": [], "lines": list(lines), "triangles": [], "texts": [], "models": []}


def plan_messages(t_s: float, trajectory: Any, report: dict[str, Any] | None) -> list[Message]:
    """The plan at time ``t_s`` [s]: /falcon/plan (``trajectory``, a Trajectory, as JSON and the
    planner's ``report`` dict or None) and /falcon/plan/path (its positions, at most about 500
    poses, in the base frame)."""
    body = {"trajectory": trajectory.to_dict(), "report": report, "duration_s": float(trajectory.duration_s)}
    step = max(1, len(trajectory.t_s) // 500)
    positions = np.vstack([trajectory.position_m[::step], trajectory.position_m[-1:]])
    path = {"timestamp": stamp(t_s), "frame_id": BASE_FRAME,
            "poses": [{"position": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}, "orientation": _IDENTITY}
                      for p in positions]}
    return [(PLAN_TOPIC, t_s, dumps(body)), (PLAN_PATH_TOPIC, t_s, dumps(path))]


__all__ = ["command_limit_of", "encoder_params_of", "model_metadata", "BASE_FRAME", "LOG_META_NAME", "Message", "RowEncoder", "SCHEMAS", "TOPICS",
           "VIEW_RATE_HZ", "WORLD_FRAME", "dumps", "plan_messages", "schema_bytes", "stamp", "transform"]
