"""Capacity of the Zenoh service under load: plans per second and latency for 1, 2 and 4
planning workers on one instance and for 1 and 2 instances, at 4 and 16 concurrent clients,
against a bare Zenoh echo queryable measured in the same run.

Setup: every configuration's instances run at once as child processes (``python -m
service.main --device none --plan-cache 0``, the real planner, peer mode on loopback, one
prefix per configuration; a second instance connects to the first). The echo is a bare Zenoh
queryable in its own child process that answers each request with its bytes padded to the
size of a plan reply. The benchmark process measures the configurations in turn, round after
round (medians reported), so a change in the machine's load hits them all alike. Clients are
threads, each with its own Zenoh session connected to the configuration's first instance,
sending its share of the requests one after the other on the shared key ``<prefix>/plan``
(the instances agree on one to answer each). Every request asks for a
different goal (the plan cache is off anyway), so every one is planned.

Nothing may be lost: every request must get exactly one reply, with its own ``request_id``
and a trajectory from its start to its goal; the script exits 1 otherwise. Latencies are
client-side round trips [ms]; plans/s = requests / wall time of the configuration.

``--router`` puts each configuration's instances and clients in client mode behind its own
``falcon-plan router`` instead of peering them. ``--pool`` measures instead why the workers are processes: the planning pool alone (no Zenoh),
1 and 2 workers as threads and as processes, the same jobs all queued at once, interleaved
rounds; plans/s against 1 thread.

Usage: ``python benchmarks/bench_load.py [--requests 48] [--rounds 3] [--pool] [--json OUT]``; run it
with ``nice`` on a shared machine and read the ratios (to the echo, and between
configurations), not the absolute figures.
"""
from __future__ import annotations

import argparse
import json
import os
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

PREFIX = "falconload"
ECHO_KEY = f"{PREFIX}/echo"
PAD_TO_BYTES = 12_000
"""Echo replies are padded to about the size of a plan reply (24 intervals)."""
HOME_M = (0.0, 0.0, 0.1448)


def echo_main(endpoint: str) -> int:
    """The bare echo queryable (child process) until its stdin closes."""
    import zenoh

    from service.config import SessionSettings, open_session

    with open_session(SessionSettings.server([endpoint])) as session:
        def echo(query: Any) -> None:
            body = query.payload.to_bytes()
            query.reply(ECHO_KEY, body + b" " * max(0, PAD_TO_BYTES - len(body)),
                        encoding=zenoh.Encoding.APPLICATION_JSON)
            query.drop()

        queryable = session.declare_queryable(ECHO_KEY, echo, complete=True)
        print("ready", flush=True)
        sys.stdin.read()
        queryable.undeclare()
    return 0


def goals(n: int, seed: int) -> list[tuple[float, float, float]]:
    """n distinct reachable goals 10-30 mm from home (seeded)."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        d = rng.normal(size=3)
        d *= rng.uniform(0.01, 0.03) / np.linalg.norm(d)
        out.append(tuple(float(round(v, 5)) for v in np.add(HOME_M, d)))
    return out


class Servers:
    """Child processes started for one configuration; stopped on exit."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, argv: list[str]) -> None:
        env = {**os.environ, "PYTHONPATH": str(ROOT), "FALCON_PLAN_LOG": "WARNING"}
        proc = subprocess.Popen([sys.executable, *argv], stdout=subprocess.PIPE, stdin=subprocess.PIPE,
                                env=env, text=True, cwd=ROOT)
        self.procs.append(proc)
        line = proc.stdout.readline() if proc.stdout else ""
        if "ready" not in line:
            raise RuntimeError(f"{argv} did not start: {line!r}")

    def __enter__(self) -> "Servers":
        return self

    def __exit__(self, *exc: Any) -> None:
        for proc in reversed(self.procs):
            if proc.stdin:
                proc.stdin.close()
            proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()


def run_clients(endpoint: str, key: str, bodies: list[bytes], clients: int, check: Any,
                mode: str = "peer") -> dict[str, Any]:
    """Send ``bodies`` from ``clients`` threads (own sessions); latency and loss figures."""
    import zenoh

    from service.config import SessionSettings, open_session

    sessions = [open_session(SessionSettings.client([endpoint], mode=mode)) for _ in range(clients)]
    time.sleep(0.5)  # gossip: every session reaches every instance
    latencies: list[float] = []
    replies: list[tuple[int, list[Any]]] = []
    lock = threading.Lock()
    barrier = threading.Barrier(clients + 1)

    def client(k: int) -> None:
        session = sessions[k]
        mine = list(range(k, len(bodies), clients))
        barrier.wait()
        for i in mine:
            t0 = time.perf_counter()
            got = [(r.ok.payload.to_bytes() if r.ok is not None else None)
                   for r in session.get(key, payload=bodies[i], timeout=120.0,
                                        encoding=zenoh.Encoding.APPLICATION_JSON,
                                        consolidation=zenoh.ConsolidationMode.NONE)]
            dt = time.perf_counter() - t0
            with lock:
                latencies.append(dt)
                replies.append((i, got))

    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
    for t in threads:
        t.start()
    barrier.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    for s in sessions:
        s.close()
    lost = sum(1 for i, got in replies if len(got) != 1 or got[0] is None or not check(i, got[0]))
    lost += len(bodies) - len(replies)
    lat = np.asarray(latencies) * 1e3
    return {"requests": len(bodies), "clients": clients, "lost": lost, "wall_s": wall,
            "per_s": len(bodies) / wall, "p50_ms": float(np.percentile(lat, 50)),
            "p99_ms": float(np.percentile(lat, 99))}


def pool_throughput(processes: bool, workers: int, jobs: int, seed: int) -> float:
    """Plans/s of a planning pool given ``jobs`` distinct plans at once (no Zenoh)."""
    from falcon_plan.planning.problem import PlanProblem
    from service.handlers import falcon_planner
    from service.workers import PlanJob, PlanningPool

    pool = PlanningPool(workers, falcon_planner, processes=processes, max_pending=jobs)
    pool.start()
    done = threading.Semaphore(0)
    try:
        t0 = time.perf_counter()
        for goal in goals(jobs, seed):
            # no warm starts: thread pools would share this process's store across pools
            pool.submit(PlanJob(PlanProblem(HOME_M, goal), {"warm_start": "none"}, time.monotonic() + 600,
                                lambda _job, _outcome: done.release()))
        for _ in range(jobs):
            done.acquire()
        return jobs / (time.perf_counter() - t0)
    finally:
        pool.close()


def pool_main(jobs: int, rounds: int) -> int:
    """Threads against processes in the planning pool alone."""
    configs = [(False, 1), (False, 2), (True, 1), (True, 2)]
    runs: dict[tuple[bool, int], list[float]] = {c: [] for c in configs}
    for rnd in range(rounds):
        for processes, workers in configs:
            runs[(processes, workers)].append(pool_throughput(processes, workers, jobs, 1000 + rnd))
            print(f"round {rnd + 1}: {workers} {'process' if processes else 'thread'}(es): "
                  f"{runs[(processes, workers)][-1]:.1f} plans/s", flush=True)
    base = float(np.median(runs[(False, 1)]))
    print(f"\nmedians over {rounds} rounds of {jobs} plans, ratio to 1 thread:")
    for (processes, workers), values in runs.items():
        med = float(np.median(values))
        print(f"  {workers} {'processes' if processes else 'threads  '}: {med:6.1f} plans/s  {med / base:.2f}x")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=48, help="requests per measurement (default 48)")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds (default 3)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--clients", type=int, nargs="+", default=[4, 16])
    parser.add_argument("--pool", action="store_true", help="threads against processes, planning pool alone")
    parser.add_argument("--router", action="store_true",
                        help="instances and clients in client mode through a `falcon-plan router` (default: peers)")
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--echo", help=argparse.SUPPRESS)  # child: run the echo on this endpoint
    args = parser.parse_args(argv)
    if args.echo:
        return echo_main(args.echo)
    if args.pool:
        return pool_main(args.requests, args.rounds)

    from service.config import free_loopback_port

    def ep() -> str:
        return f"tcp/127.0.0.1:{free_loopback_port()}"

    # every configuration runs at once, each under its own prefix, and they are measured in
    # turn, round after round, so a change of the machine's load hits them all alike
    configs = [("echo", 1, 0)] + [("service", 1, w) for w in args.workers] + [("service", 2, 1)]
    samples: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    seed = 0
    mode = "client" if args.router else "peer"
    with Servers() as servers:
        endpoints = {}
        for what, instances, workers in configs:
            first = ep()
            endpoints[(what, instances, workers)] = first
            if what == "echo":
                servers.start([__file__, "--echo", first])
                continue
            prefix = f"{PREFIX}{instances}x{workers}"
            if args.router:  # every instance and client joins this router in client mode
                servers.start(["-m", "falcon_plan.cli", "router", "--listen", first])
            for k in range(instances):
                where = (["--mode", "client", "--connect", first] if args.router else
                         ["--listen", first if k == 0 else ep(), *(["--connect", first] if k else [])])
                servers.start(["-m", "service.main", "--device", "none", "--prefix", prefix, "--instance", f"load{k}",
                               "--planning-workers", str(workers), "--plan-cache", "0", *where])
        for rnd in range(args.rounds):
            for clients in args.clients:
                for config in configs:
                    what, instances, workers = config
                    seed += 1
                    gs = goals(args.requests, seed)
                    bodies = [json.dumps({"start_m": list(HOME_M), "goal_m": list(g), "request_id": f"q{i}",
                                          "timeout_s": 120.0}).encode() for i, g in enumerate(gs)]

                    def check(i: int, raw: bytes, gs: Any = gs, echo: bool = what == "echo") -> bool:
                        body = json.loads(raw)
                        if echo:
                            return body["request_id"] == f"q{i}"
                        pos = body["trajectory"]["position_m"]
                        return (body["request_id"] == f"q{i}" and np.allclose(pos[0], HOME_M, atol=1e-6)
                                and np.allclose(pos[-1], gs[i], atol=1e-6))

                    key = ECHO_KEY if what == "echo" else f"{PREFIX}{instances}x{workers}/plan"
                    row = run_clients(endpoints[config], key, bodies, clients, check,
                                      mode if what == "service" else "peer")
                    samples.setdefault((*config, clients), []).append(row)
                    print(f"round {rnd + 1}: " + _fmt({"what": what, "instances": instances, "workers": workers,
                                                        **row}), flush=True)

    rows = []
    for (what, instances, workers, clients), runs in samples.items():
        rows.append({"what": what, "instances": instances, "workers": workers, "clients": clients,
                     "requests": sum(r["requests"] for r in runs), "lost": sum(r["lost"] for r in runs),
                     "per_s": float(np.median([r["per_s"] for r in runs])),
                     "p50_ms": float(np.median([r["p50_ms"] for r in runs])),
                     "p99_ms": float(np.median([r["p99_ms"] for r in runs]))})
    base = {r["clients"]: r for r in rows if r["what"] == "service" and r["instances"] == 1 and r["workers"] == 1}
    echo = {r["clients"]: r for r in rows if r["what"] == "echo"}
    print(f"\nmedians over {args.rounds} rounds of {args.requests} requests; speedup = plans/s over 1 instance x "
          "1 worker at the same clients; p50 / echo = p50 over the echo's p50")
    print("what     inst workers clients   per_s   p50_ms   p99_ms  speedup  p50/echo  lost")
    for r in sorted(rows, key=lambda r: (r["clients"], r["what"], r["instances"], r["workers"])):
        if r["what"] == "service":
            r["speedup"] = r["per_s"] / base[r["clients"]]["per_s"]
            r["p50_over_echo"] = r["p50_ms"] / echo[r["clients"]]["p50_ms"]
        print(f"{r['what']:8s} {r['instances']:4d} {r['workers']:7d} {r['clients']:7d} {r['per_s']:7.1f} "
              f"{r['p50_ms']:8.1f} {r['p99_ms']:8.1f} {r.get('speedup', float('nan')):8.2f} "
              f"{r.get('p50_over_echo', float('nan')):9.0f} {r['lost']:5d}")
    if args.json:
        Path(args.json).write_text(json.dumps({"cpus": os.cpu_count(), "rows": rows}, indent=2))
    lost = sum(r["lost"] for r in rows)
    print(f"\nlost: {lost} of {sum(r['requests'] for r in rows)} requests (machine: {os.cpu_count()} cores)")
    return 1 if lost else 0


def _fmt(r: dict[str, Any]) -> str:
    return (f"{r['what']:7s} {r['instances']} inst x {r['workers']} workers, {r['clients']:2d} clients: "
            f"{r['per_s']:7.1f} /s  p50 {r['p50_ms']:7.1f} ms  p99 {r['p99_ms']:7.1f} ms  lost {r['lost']}")


if __name__ == "__main__":
    sys.exit(main())
