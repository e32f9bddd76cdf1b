"""The layers hold: the import-linter contracts of pyproject.toml are kept, no module takes
part in an import cycle (function-level imports count), the robot loads nothing of the
cloud side, docs/internals.md names every module, and no class grows past 400 lines."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import grimp
from conftest import small_scene

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "fleetslam"
CLOUD_LIBRARIES = ("gtsam", "faiss", "small_gicp", "scipy", "octomap", "matplotlib",
                   "cryptography", "mcap")


def test_the_layer_contracts_are_kept():
    # In its own process: import-linter's command line reconfigures logging.
    lint = subprocess.run([str(Path(sys.executable).with_name("lint-imports")), "--config",
                           str(ROOT / "pyproject.toml"), "--no-cache"], cwd=ROOT,
                          capture_output=True, text=True)
    assert lint.returncode == 0, lint.stdout + lint.stderr
    assert "0 broken" in lint.stdout


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of ``graph`` (module -> modules it imports): its strongly connected
    components of more than one module (Tarjan, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def test_every_module_is_named_on_the_internals_page_and_every_path_it_names_exists():
    """docs/internals.md walks a frame through the code and lays out every package: a module
    it does not name is one a newcomer cannot find, and a path it names that is gone sends
    them nowhere."""
    import re

    page = (ROOT / "docs" / "internals.md").read_text()
    package = ROOT / "src" / "fleetslam"
    unnamed = [str(p.relative_to(package)) for p in sorted(package.rglob("*.py"))
               if p.name != "__init__.py" and p.name not in page]
    assert not unnamed, f"modules docs/internals.md does not name: {unnamed}"
    named = set(re.findall(r"`((?:[a-z_0-9]+/)+[a-z_0-9]+\.py)`", page))
    gone = sorted(p for p in named if not (package / p).is_file() and not (ROOT / p).is_file())
    assert named and not gone, f"paths docs/internals.md names that do not exist: {gone}"


def test_no_module_takes_part_in_an_import_cycle():
    built = grimp.build_graph("fleetslam", cache_dir=None)
    graph = {m: built.find_modules_directly_imported_by(m) for m in built.modules}
    assert strongly_connected(graph) == []
    # The check finds cycles (two modules, and one through a function-level import).
    assert strongly_connected({"a": {"b"}, "b": {"a"}, "c": set()}) == [["a", "b"]]
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set()}) \
        == [["a", "b", "c"]]


def test_the_robot_loads_nothing_of_the_cloud_side():
    code = ("import sys, fleetslam.edge.robot, fleetslam.cli; "
            f"print(sorted(m for m in {CLOUD_LIBRARIES!r} if m in sys.modules)); "
            "print(sorted(m for m in sys.modules if m.startswith(('fleetslam.backend', "
            "'fleetslam.cloud', 'fleetslam.merging', 'fleetslam.mapping'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert out == ["[]", "[]"]


def test_the_base_install_is_what_a_robot_needs():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = {d.split(">")[0].split("=")[0].strip() for d in project["dependencies"]}
    assert names == {"numpy", "opencv-python-headless", "eclipse-zenoh", "zstandard"}
    cloud = {d.split(">")[0].strip() for d in project["optional-dependencies"]["cloud"]}
    assert {"gtsam", "small_gicp", "faiss-cpu", "scipy", "octomap-python"} <= cloud


def test_without_the_cloud_extra_the_robot_runs_and_the_rest_says_what_it_needs(
        tmp_path_factory):
    """A robot's install, simulated by making the cloud's libraries unimportable: the robot
    and its pipeline import; `fleetslam run` and a robot tracking by itself (point 6) name the
    extra they need instead of a traceback."""
    source = small_scene(tmp_path_factory, 2)[0]
    out = tmp_path_factory.mktemp("run") / "out"
    code = f"""
import sys
for name in {CLOUD_LIBRARIES!r}:
    sys.modules[name] = None  # import raises ModuleNotFoundError
from fleetslam.cli import main
import fleetslam.edge.robot, fleetslam.pipeline.front_end, fleetslam.wire.frames
print(main(["run", "--robot", "{source}", "--out", "{out}"]))
print(main(["robot", "--id", "r1", "--source", "{source}", "--offload-at", "6"]))
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.stdout.split() == ["2", "2"], run.stderr
    assert "`fleetslam run` needs the cloud extra: pip install 'fleetslam[cloud]'" in run.stderr
    assert "(--offload-at 6) runs the back-end, which needs the cloud extra" in run.stderr


def test_no_class_in_src_is_over_400_lines():
    """A class past ~400 lines is split by concern (the house rule; RobotSession had grown
    to 748)."""
    import ast

    over = []
    for path in sorted(SRC.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > 400:
                over.append(f"{path.relative_to(SRC)}: {node.name} "
                            f"{node.end_lineno - node.lineno + 1} lines")
    assert not over, over


def test_the_cloud_keeps_its_concerns_in_subpackages():
    """cloud/ holds its three concerns in subpackages (session, coordination, merge) and at
    most 10 files at its top level."""
    top = [p.name for p in (SRC / "cloud").glob("*.py")]
    assert len(top) <= 10, top
    assert {"session", "coordination", "merge"} <= {p.name for p in (SRC / "cloud").iterdir()
                                                    if (p / "__init__.py").exists()}
