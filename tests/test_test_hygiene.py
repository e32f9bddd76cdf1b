"""The tests themselves: none asserts how fast the machine is. A measured duration may be
held to a lower bound (the test waited for a deadline: load only makes it longer) or to a
hang guard (``HANG_S`` or a bound of at least that many seconds, failing only when something
hangs), never to an upper bound near what it takes: a loaded CI machine takes 2-5x longer.
"""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent
CLOCKS = {"monotonic", "perf_counter", "time"}
# Names that hold a duration however they were assigned (a helper's returned tuple, say).
DURATION_NAMES = {"took", "elapsed"}
# A bound at least this large (seconds) fails only on a hang, not on a slow machine.
HANG_BOUND_S = 30.0


def _is_clock_call(node: ast.AST) -> bool:
    if not isinstance(node, ast.Call):
        return False
    f = node.func
    if isinstance(f, ast.Attribute):
        return f.attr in CLOCKS and isinstance(f.value, ast.Name) and f.value.id == "time"
    return isinstance(f, ast.Name) and f.id in ("monotonic", "perf_counter")


class _Durations(ast.NodeVisitor):
    """Per function: names holding a clock reading, names holding a duration, and the
    asserted upper bounds on a duration that are not hang guards."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.found: list[str] = []
        self.readings: set[str] = set()
        self.durations: set[str] = set()

    def visit_FunctionDef(self, node: ast.FunctionDef) -> None:
        outer = self.readings, self.durations
        self.readings, self.durations = set(), set()
        for sub in ast.walk(node):  # a first pass: what each name holds
            if isinstance(sub, (ast.Assign, ast.AnnAssign)) and sub.value is not None:
                targets = sub.targets if isinstance(sub, ast.Assign) else [sub.target]
                names = [n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)]
                values = (sub.value.elts if isinstance(sub.value, ast.Tuple)
                          else [sub.value] * len(names))
                for name, value in zip(names, values):
                    if _is_clock_call(value):
                        self.readings.add(name)
                    elif self._is_duration(value):
                        self.durations.add(name)
        self.generic_visit(node)
        self.readings, self.durations = outer

    def _is_duration(self, node: ast.AST) -> bool:
        for sub in ast.walk(node):
            if isinstance(sub, ast.Name) and sub.id in self.durations | DURATION_NAMES:
                return True
            if isinstance(sub, ast.BinOp) and isinstance(sub.op, ast.Sub):
                sides = (sub.left, sub.right)
                if any(_is_clock_call(s) or (isinstance(s, ast.Name) and s.id in self.readings)
                       for s in sides):
                    return True
        return False

    def visit_Assert(self, node: ast.Assert) -> None:
        for compare in (n for n in ast.walk(node.test) if isinstance(n, ast.Compare)):
            operands = [compare.left, *compare.comparators]
            for (a, b), op in zip(zip(operands, operands[1:]), compare.ops):
                small, bound = ((a, b) if isinstance(op, (ast.Lt, ast.LtE)) else
                                (b, a) if isinstance(op, (ast.Gt, ast.GtE)) else (None, None))
                if small is not None and self._is_duration(small) and not _hang_guard(bound):
                    self._flag(node, "an upper bound on a duration")
                if isinstance(op, ast.Eq) and any(self._is_duration(s) for s in (a, b)) \
                        and any(_is_approx(s) for s in (a, b)):
                    self._flag(node, "a duration compared with approx")

    def _flag(self, node: ast.AST, what: str) -> None:
        self.found.append(f"{self.path.name}:{node.lineno}: {what}: {ast.unparse(node)}")


def _is_approx(node: ast.AST) -> bool:
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and node.func.attr == "approx")


def _hang_guard(bound: ast.AST) -> bool:
    if any(isinstance(n, ast.Name) and "HANG" in n.id for n in ast.walk(bound)):
        return True
    return (isinstance(bound, ast.Constant) and isinstance(bound.value, (int, float))
            and bound.value >= HANG_BOUND_S)


def wall_clock_bounds(source: str, path: Path) -> list[str]:
    visitor = _Durations(path)
    visitor.visit(ast.parse(source))
    return visitor.found


def test_no_test_asserts_an_upper_bound_on_wall_clock_time():
    found = [line for path in sorted(TESTS.glob("*.py"))
             for line in wall_clock_bounds(path.read_text(), path)]
    assert not found, "tests that fail on a loaded machine:\n" + "\n".join(found)


def test_the_scan_finds_the_forms_that_failed_and_passes_the_ones_allowed():
    flagged = '''
def f(link, slow):
    start = time.monotonic()
    while slow.take(5.0) is not None:
        taken += 1
    elapsed = time.monotonic() - start
    assert abs(taken - elapsed * 10) <= 3
    assert 2.7 < elapsed < 3.6
    assert time.perf_counter() - start < 2.0
    assert elapsed == pytest.approx(1.0, rel=0.15)
    assert received.times[0] - start == pytest.approx(0.2, abs=0.05)
    done, took = fleetslam(["status"])
    assert took < 15
'''
    allowed = '''
def f(slot):
    start = time.monotonic()
    slot.take(0.1)
    assert time.monotonic() - start >= 0.09
    took = time.monotonic() - start
    assert took < HANG_S and took < 60
    assert fake.t == pytest.approx(1.0)
    assert len(items) < 2.0
'''
    assert len(wall_clock_bounds(flagged, Path("flagged.py"))) == 6
    assert wall_clock_bounds(allowed, Path("allowed.py")) == []
