"""All force on a device goes through one loop with one set of guards (issue 23, item 8): the
executor's run, the hold before it and the doctor's paced loop each drive the device through a
:class:`~falcon_plan.execution.force_loop.ForceLoop`; nothing else in the library or the service
builds the guards or sends a device anything but zero force."""
from __future__ import annotations

import ast
import time
from pathlib import Path

import numpy as np

import falcon_plan
from falcon_plan.execution.executor import ExecutionStatus, Executor
from falcon_plan.execution.force_loop import ForceLoop
from falcon_plan.execution.holding import HoldLoop
from falcon_plan.execution.paced import PacedLoop
from falcon_plan.execution.safety import SafetyConfig

from .conftest import FaultyDevice

RATE = 1000.0
ROOT = Path(falcon_plan.__file__).parent.parent
GUARDS = ("WatchedExchange", "TickGuard")
"""The per-tick guards: built by the force loop only."""
DRIVERS = ("falcon_plan/devices/", "falcon_plan/execution/safety.py", "falcon_plan/execution/force_loop.py")
"""Where a device's exchange is defined or guarded."""
PROXIES = {("service/device.py", "_RecordingDevice")}
"""Wrappers that pass a caller's exchange on to the device they wrap."""


def _sources() -> list[Path]:
    return sorted([*(ROOT / "falcon_plan").rglob("*.py"), *(ROOT / "service").rglob("*.py")])


def _called(node: ast.Call) -> str | None:
    return getattr(node.func, "attr", getattr(node.func, "id", None))


def _zero_literal(node: ast.expr) -> bool:
    """``np.zeros(...)``, ``[0, 0, 0]`` or ``(0, 0, 0)``."""
    if isinstance(node, ast.Call):
        return _called(node) == "zeros"
    if isinstance(node, (ast.List, ast.Tuple)):
        return all(isinstance(e, ast.Constant) and e.value == 0 for e in node.elts)
    return False


def _force_sent_outside_the_loop(path: Path, root: Path = ROOT) -> list[str]:
    """Each place in ``path`` (under ``root``) that builds a guard or exchanges anything but zero
    with a device (``relative:line: what``), skipping the drivers and the pass-through proxies."""
    rel = path.relative_to(root).as_posix()
    if rel.startswith(DRIVERS):
        return []
    tree = ast.parse(path.read_text(), str(path))
    proxied = {id(n) for cls in ast.walk(tree) if isinstance(cls, ast.ClassDef) and (rel, cls.name) in PROXIES
               for n in ast.walk(cls)}
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call) or id(node) in proxied:
            continue
        name = _called(node)
        if name in GUARDS:
            found.append(f"{rel}:{node.lineno}: builds a {name}")
        elif name == "exchange" and isinstance(node.func, ast.Attribute) and not (node.args and _zero_literal(node.args[0])):
            found.append(f"{rel}:{node.lineno}: exchanges {ast.unparse(node.args[0]) if node.args else '?'}")
    return found


def test_only_the_force_loop_builds_the_guards_or_sends_a_device_force() -> None:
    sources = _sources()
    assert len(sources) > 60
    offending = [line for path in sources for line in _force_sent_outside_the_loop(path)]
    assert offending == []


def test_the_scan_sees_a_guard_built_and_force_sent_elsewhere(tmp_path: Path) -> None:
    """The scan is not blind: a module that builds a guard and sends a command is found, one that
    only reads at zero force is not."""
    probe = tmp_path / "falcon_plan" / "probe.py"
    probe.parent.mkdir()
    probe.write_text("import numpy as np\n"
                     "def f(device, tc):\n"
                     "    g = TickGuard(1, 2, 3, 4)\n"
                     "    device.exchange(np.zeros(3))\n"
                     "    device.exchange([0, 0, 0])\n"
                     "    return device.exchange(tc)\n")
    assert _force_sent_outside_the_loop(probe, tmp_path) == ["falcon_plan/probe.py:3: builds a TickGuard",
                                                            "falcon_plan/probe.py:6: exchanges tc"]


def test_every_exchange_of_a_held_run_and_of_a_diagnostic_goes_through_a_force_loop(
        model, sim_device, make_move, monkeypatch) -> None:
    """A hold, the run that takes over from it, then a doctor's paced loop on the same device:
    every exchange the device saw was a force loop's (its first read or a tick's send), three
    loops in all; the device is left at zero force."""
    through: list[ForceLoop] = []     # (the loops themselves: kept alive, their ids distinct)
    first, send = ForceLoop.first, ForceLoop.send

    def counted_first(self: ForceLoop, commands):
        through.append(self)
        return first(self, commands)

    def counted_send(self: ForceLoop, commands, slot: int):
        through.append(self)
        return send(self, commands, slot)

    monkeypatch.setattr(ForceLoop, "first", counted_first)
    monkeypatch.setattr(ForceLoop, "send", counted_send)
    dev = FaultyDevice(sim_device(RATE), at=10**9, fault="jump", realtime=True)
    executor = Executor(dev, model, pace=True)
    with HoldLoop(executor) as hold:
        assert hold.wait_settled()
        report = executor.run(make_move(rate_hz=RATE), hold=hold)
    assert report.status == ExecutionStatus.COMPLETED, report.reason
    with PacedLoop(dev, model) as loop:
        for _ in range(50):
            slot = loop.wait(loop.slot)
            loop.send(np.zeros(3), slot)
            loop.slot = slot + 1
    assert report.samples > 0 and hold.ticks > 0
    assert dev.exchanges == len(through) >= report.samples + hold.ticks + 51
    assert len({id(loop) for loop in through}) == 3
    assert dev.last_sent == [0, 0, 0]


class _ZeroFails(FaultyDevice):
    """A device whose zero_force raises (a USB write that fails at the end)."""

    def zero_force(self) -> None:
        super().zero_force()
        raise OSError("write failed")


def test_the_loops_end_never_raises_and_says_why_zero_force_failed(model, sim_device) -> None:
    dev = _ZeroFails(sim_device(RATE), at=10**9, fault="jump")
    loop = ForceLoop(dev, model, SafetyConfig(), RATE, timer=None)
    loop.first(np.zeros(3))
    loop.begin(watch=False)    # (a watchdog's trip on a loaded machine would zero the force too)
    loop.send(np.array([100, 0, 0]), 0)
    problem = loop.end()
    assert isinstance(problem, OSError) and len(dev.zero_calls) == 1
    assert loop.end(zero_force=False) is None and len(dev.zero_calls) == 1   # asked not to: untouched
    assert isinstance(loop.end(), OSError) and len(dev.zero_calls) == 2      # again: tried again


def test_an_unpaced_loop_dates_a_reading_by_the_hand_overs_before_it(model, sim_device) -> None:
    """Without deadlines the loop notes when each tick's command was handed over: a reading that
    arrived after slot k's hand-over was read for slot k + 1; one from before every noted
    hand-over is older than all of them (-1); an unknown arrival says nothing (None)."""
    dev = FaultyDevice(sim_device(RATE), at=10**9, fault="jump")
    loop = ForceLoop(dev, model, SafetyConfig(), RATE, timer=None)
    assert loop.read_for(time.monotonic()) is None        # nothing handed over yet
    loop.first(np.zeros(3))
    before = time.monotonic()
    for slot in range(3):
        loop.send(np.zeros(3), slot)
    assert loop.read_for(time.monotonic()) == 3
    assert loop.read_for(before) == -1
    assert loop.read_for(None) is None
    assert loop.last_slot == 2 and before <= loop.sent_s <= time.monotonic()
    loop.end()
