"""A pytest plugin that says where the suite's time goes: per test, wall seconds and the
seconds XLA spent compiling in this process (jax.monitoring's backend compile events;
subprocesses a test starts are wall time only).

    PYTHONPATH=tests python -m pytest -q -n 0 -p compile_profile [--compile-profile-json F]

prints the 25 longest tests and the totals at the end; the JSON (test id -> [wall s,
compile s, trace and lowering s, compiles]) keeps every test. docs/testing.md has the
figures it gave.
"""

from __future__ import annotations

import collections
import json
import time

import pytest

COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = ("/jax/core/compile/jaxpr_trace_duration",
         "/jax/core/compile/jaxpr_to_mlir_module_duration")

_current = ["<collection>"]
_rows: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0, 0.0, 0])


def _listener(event: str, duration: float, **_) -> None:
    row = _rows[_current[0]]
    if event == COMPILE:
        row[1] += duration
        row[3] += 1
    elif event in TRACE:
        row[2] += duration


def pytest_addoption(parser):
    parser.addoption("--compile-profile-json", default=None,
                     help="write every test's [wall, compile, trace+lower, compiles] here")


def pytest_configure(config):
    import jax
    jax.monitoring.register_event_duration_secs_listener(_listener)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _current[0] = item.nodeid
    start = time.perf_counter()
    yield
    _rows[item.nodeid][0] += time.perf_counter() - start


def pytest_terminal_summary(terminalreporter, config):
    rows = sorted(_rows.items(), key=lambda kv: -kv[1][0])
    wall, comp, trace = (sum(r[i] for _, r in rows) for i in range(3))
    write = terminalreporter.write_line
    write(f"compile profile: {wall:.0f} s in tests, {comp:.0f} s of it XLA compiling "
          f"({sum(r[3] for _, r in rows)} compiles), {trace:.0f} s tracing and lowering")
    write("  wall   compile  compiles  test")
    for name, (w, c, _, n) in rows[:25]:
        write(f"{w:6.1f} {c:8.1f} {n:9d}  {name}")
    path = config.getoption("--compile-profile-json")
    if path:
        with open(path, "w") as f:
            json.dump(dict(rows), f, indent=0)
