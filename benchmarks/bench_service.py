"""Load on the Zenoh service: many concurrent plan requests, none lost or mixed up, and the
service's own overhead measured against a bare Zenoh echo queryable in the same run.

Setup: a child process (this script with ``--serve``) runs one planning-only instance
(``--device none``, the real planner) and a bare echo queryable on the service's own session
that replies with the request bytes padded with spaces to the size of a plan reply (still
valid JSON). The benchmark process runs ``--clients`` threads, each with its own Zenoh session
(peer, loopback, multicast off), sending ``--requests`` gets each; replies are checked after
the clock stops, so client-side parsing does not slow the other clients.

1. Warm-up: each of ``--goals`` distinct moves is planned once (the planner's time is
   reported apart, from the replies' ``timing.plan_s``).
2. Echo: the same request bodies to the echo queryable, same concurrency.
3. Service: the same request bodies to ``P/I/plan``; they are answered from the instance's
   plan cache, so the latency is transport + decoding, schema and workspace checks, cache
   lookup and encoding: the service's overhead without the planner.

Every reply is checked: one reply per request, ``request_id`` equal to the request's, and the
trajectory starting at the request's start and ending at its goal. Latency percentiles are
client-side round trips [ms]; overhead = service - echo at the same percentile.

Usage: ``python benchmarks/bench_service.py [--clients 4] [--requests 150] [--goals 8]
[--json OUT]``. Run it with ``nice`` on a shared machine; read the difference, not the
absolutes.
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

PREFIX = "falconbench"
INSTANCE = "bench0"
ECHO_KEY = f"{PREFIX}/echo"
PAD_TO_BYTES = 14_000
"""Echo replies are padded to about the size of a plan reply (30 intervals: ~14 kB)."""


# --- the server side (child process) ------------------------------------------------------------
def serve(endpoint: str) -> int:
    """Run the instance and the echo queryable until SIGINT/SIGTERM."""
    import zenoh

    from service.config import SessionSettings
    from service.handlers import falcon_planner
    from service.keys import ServiceKeys
    from service.options import ServiceOptions
    from service.server import FalconService

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    service = FalconService(SessionSettings.server([endpoint]), ServiceKeys(PREFIX, INSTANCE),
                            falcon_planner, None, ServiceOptions(max_pending_plans=1024))

    def echo(query: Any) -> None:
        with query:
            body = query.payload.to_bytes()
            query.reply(ECHO_KEY, body + b" " * max(0, PAD_TO_BYTES - len(body)),
                        encoding=zenoh.Encoding.APPLICATION_JSON)

    with service:
        gc.freeze()  # as `serve` does: startup objects out of the collector's way
        # on the service's own session: same process, same transport, no service code
        queryable = service.session.declare_queryable(ECHO_KEY, echo, complete=True)
        token = service.session.liveliness().declare_token(f"{PREFIX}/alive/bench-echo")
        stop.wait()
        token.undeclare()
        queryable.undeclare()
    return 0


# --- the client side ----------------------------------------------------------------------------
def _moves(n: int) -> list[tuple[list[float], list[float]]]:
    """``n`` distinct start/goal pairs inside the workspace, 15-40 mm apart (seeded)."""
    from falcon_plan.model.workspace import in_workspace

    rng = np.random.default_rng(7)
    centre = np.array([0.0, 0.0, 0.135])
    moves: list[tuple[list[float], list[float]]] = []
    while len(moves) < n:
        start = centre + rng.uniform(-0.015, 0.015, 3)
        goal = start + rng.uniform(-0.025, 0.025, 3)
        if in_workspace(start) and in_workspace(goal) and 0.015 < np.linalg.norm(goal - start) < 0.04:
            moves.append(([round(v, 5) for v in start], [round(v, 5) for v in goal]))
    return moves


def _run_clients(endpoint: str, key: str, moves: list[tuple[list[float], list[float]]], clients: int,
                 requests: int, check_plan: bool) -> dict[str, Any]:
    """``clients`` threads x ``requests`` gets on ``key``; latencies and checks."""
    import zenoh

    from service.config import SessionSettings, open_session

    latencies: list[float] = []
    problems: list[str] = []
    spans: list[tuple[float, float]] = []
    lock = threading.Lock()
    barrier = threading.Barrier(clients)

    def worker(c: int) -> None:
        mine: list[float] = []
        bad: list[str] = []
        received: list[tuple[str, list[float], list[float], bytes]] = []
        payloads = []
        for i in range(requests):
            start, goal = moves[(c + i) % len(moves)]
            rid = f"c{c}-r{i}"
            payloads.append((rid, start, goal, json.dumps({"request_id": rid, "start_m": start,
                                                           "goal_m": goal}).encode()))
        with open_session(SessionSettings.client([endpoint])) as session:
            barrier.wait()
            began = time.perf_counter()
            for rid, start, goal, payload in payloads:
                t0 = time.perf_counter()
                replies = list(session.get(key, payload=payload, encoding=zenoh.Encoding.APPLICATION_JSON,
                                           timeout=30.0))
                mine.append(time.perf_counter() - t0)
                if len(replies) != 1 or replies[0].ok is None:
                    bad.append(f"{rid}: {len(replies)} replies" + (" (error)" if replies else ""))
                else:
                    received.append((rid, start, goal, replies[0].ok.payload.to_bytes()))
            ended = time.perf_counter()
        # checked after the clock stops, so client-side parsing does not load the other clients
        for rid, start, goal, raw in received:
            body = json.loads(raw)
            if body.get("request_id") != rid:
                bad.append(f"{rid}: answered as {body.get('request_id')}")
            elif check_plan:
                pos = body["trajectory"]["position_m"]
                if not (np.allclose(pos[0], start, atol=1e-6) and np.allclose(pos[-1], goal, atol=1e-6)):
                    bad.append(f"{rid}: trajectory does not go from its start to its goal")
        with lock:
            latencies.extend(mine)
            problems.extend(bad)
            spans.append((began, ended))

    threads = [threading.Thread(target=worker, args=(c,)) for c in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = max(e for _b, e in spans) - min(b for b, _e in spans)  # sessions open before the clock
    ms = np.array(latencies) * 1e3
    return {"requests": clients * requests, "answered_ok": clients * requests - len(problems),
            "problems": problems[:10], "wall_s": wall, "throughput_per_s": len(ms) / wall,
            "p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max())}


def bench(clients: int, requests: int, n_goals: int) -> dict[str, Any]:
    """Start the server process, run the three phases, stop it; returns the results."""
    from service.client import FalconClient, wait_for_instance
    from service.config import SessionSettings, free_loopback_port

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    server = subprocess.Popen([sys.executable, __file__, "--serve", endpoint], cwd=ROOT,
                              env={**os.environ, "FALCON_PLAN_LOG": "WARNING"})
    try:
        moves = _moves(n_goals)
        with FalconClient(SessionSettings.client([endpoint]), prefix=PREFIX, instance=INSTANCE,
                          timeout_s=60) as client:
            wait_for_instance(client, INSTANCE, timeout_s=60)
            wait_for_instance(client, "bench-echo", timeout_s=10)
            plan_s, service_s = [], []
            for start, goal in moves:
                body = client.plan(start, goal, instance=INSTANCE)
                plan_s.append(body["timing"]["plan_s"])
        echo = _run_clients(endpoint, ECHO_KEY, moves, clients, requests, check_plan=False)
        service = _run_clients(endpoint, f"{PREFIX}/{INSTANCE}/plan", moves, clients, requests, check_plan=True)
        with FalconClient(SessionSettings.client([endpoint]), prefix=PREFIX, instance=INSTANCE) as client:
            for start, goal in moves:
                service_s.append(client.plan(start, goal, instance=INSTANCE)["timing"]["service_s"])
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=15)
        except subprocess.TimeoutExpired:
            server.kill()
    return {
        "clients": clients, "requests_per_client": requests, "distinct_goals": n_goals,
        "planner_cold_plan_ms": {"p50": 1e3 * statistics.median(plan_s), "max": 1e3 * max(plan_s)},
        "echo": echo, "service": service,
        "overhead_ms": {"p50": service["p50_ms"] - echo["p50_ms"], "p99": service["p99_ms"] - echo["p99_ms"]},
        "service_self_reported_ms": {"p50": 1e3 * statistics.median(service_s), "max": 1e3 * max(service_s)},
        "server_exit_code": server.returncode,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--requests", type=int, default=150, help="requests per client")
    parser.add_argument("--goals", type=int, default=8, help="distinct moves (each planned once)")
    parser.add_argument("--json", default=None, help="also write the results here")
    parser.add_argument("--serve", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        return serve(args.serve)
    res = bench(args.clients, args.requests, args.goals)
    total = res["clients"] * res["requests_per_client"]
    print(f"{res['clients']} clients x {res['requests_per_client']} plan requests ({total}), "
          f"{res['distinct_goals']} distinct moves")
    print(f"planner, cold (warm-up, apart): p50 {res['planner_cold_plan_ms']['p50']:.0f} ms, "
          f"max {res['planner_cold_plan_ms']['max']:.0f} ms")
    for name in ("echo", "service"):
        r = res[name]
        print(f"{name:8s} answered {r['answered_ok']}/{r['requests']}  p50 {r['p50_ms']:.2f} ms  "
              f"p99 {r['p99_ms']:.2f} ms  max {r['max_ms']:.2f} ms  {r['throughput_per_s']:.0f} req/s"
              + (f"  problems: {r['problems']}" if r["problems"] else ""))
    print(f"service overhead over bare echo: p50 {res['overhead_ms']['p50']:.2f} ms, "
          f"p99 {res['overhead_ms']['p99']:.2f} ms (service's own timing.service_s: p50 "
          f"{res['service_self_reported_ms']['p50']:.2f} ms)")
    print(f"server exit code after SIGINT: {res['server_exit_code']}")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2))
    ok = all(res[n]["answered_ok"] == total for n in ("echo", "service")) and res["server_exit_code"] == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
