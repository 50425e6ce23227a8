"""A pytest plugin for timing tests on a busy machine: ``python -m pytest -p cpu_durations tests/x`` prints, after the
run, the CPU seconds of the slowest tests (this process's, and those of the children it waited for: the CLI and
bench subprocesses), setup + call + teardown. Wall time (``--durations``) grows with the machine's load; CPU time
much less. Not under ``-n`` (each worker keeps its own numbers)."""

import resource
import time

import pytest

SPENT: dict[str, list[float]] = {}
"""``{nodeid: [wall seconds, own CPU seconds, children's CPU seconds]}``."""


def _clocks() -> tuple[float, float, float]:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.perf_counter(), own.ru_utime + own.ru_stime, kids.ru_utime + kids.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    start = _clocks()
    yield
    SPENT[item.nodeid] = [b - a for a, b in zip(start, _clocks())]


def pytest_terminal_summary(terminalreporter):
    rows = sorted(SPENT.items(), key=lambda kv: -(kv[1][1] + kv[1][2]))
    terminalreporter.write_sep("=", "CPU seconds per test (own + children), slowest 30")
    for nodeid, (wall, own, kids) in rows[:30]:
        terminalreporter.write_line(f"{own + kids:7.1f} cpu {kids:7.1f} children {wall:7.1f} wall  {nodeid}")
    total = sum(own + kids for _, own, kids in SPENT.values())
    terminalreporter.write_line(f"{total:7.1f} CPU seconds in {len(SPENT)} tests")
