"""A client of the falcon-plan service that knows only zenoh, JSON and service/README.md.

Usage: python raw_zenoh_client.py ENDPOINT PREFIX INSTANCE 'PLAN_REQUEST_JSON' GOAL_ID
Prints one JSON object with what each documented request returned. It must not import the
project (checked at the end), so it proves the documented keys and payloads are enough.
"""
import json
import sys
import threading

import zenoh


def get(session, key, body=None, raw=None):
    payload = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
    out = []
    for reply in session.get(key, payload=payload, encoding=zenoh.Encoding.APPLICATION_JSON, timeout=30.0):
        sample = reply.ok if reply.ok is not None else reply.err
        out.append({"ok": reply.ok is not None, "key": str(reply.ok.key_expr) if reply.ok else None,
                    "body": json.loads(sample.payload.to_bytes())})
    return out


def main(endpoint, prefix, instance, plan_request, goal_id):
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    result = {}
    with zenoh.open(conf) as session:
        base = f"{prefix}/{instance}"
        result["alive"] = sorted(str(r.ok.key_expr) for r in session.liveliness().get(f"{prefix}/alive/*", timeout=5.0)
                                 if r.ok is not None)
        result["plan"] = get(session, f"{base}/plan", json.loads(plan_request))
        result["plan_nan"] = get(session, f"{base}/plan", raw=b'{"start_m": [NaN, 0, 0.14], "goal_m": [0, 0, 0.13]}')
        result["state"] = get(session, f"{base}/state")
        result["schema"] = get(session, f"{prefix}/schema/goal_request")
        done = threading.Event()
        finals = []

        def on_result(sample):
            body = json.loads(sample.payload.to_bytes())
            if body["status"] in ("done", "failed", "cancelled"):
                finals.append(body)
                done.set()

        sub = session.declare_subscriber(f"{base}/goals/{goal_id}/result", on_result)
        session.put(f"{base}/goals/submit", json.dumps({"id": goal_id, "goal_m": [0.0, 0.0, 0.14]}).encode(),
                    encoding=zenoh.Encoding.APPLICATION_JSON)
        done.wait(30.0)
        sub.undeclare()
        result["goal"] = finals[-1] if finals else get(session, f"{base}/goals/{goal_id}/result")
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("falcon_plan", "service", "numpy"))
    result["project_modules_imported"] = leaked
    json.dump(result, sys.stdout)


if __name__ == "__main__":
    main(*sys.argv[1:6])
