"""The repository's layout, checked (issue 28): tests by part, no test module importing another,
and the import graph of the packages.

Where tests live (a new test file goes in the folder of the part it tests):
    tests/core/      onboard/core and the scenario/settings (onboard/config.py, onboard/settings/)
    tests/app/       onboard/app, `pmon run` and the onboard CLI (signing, failsafes, DF input, soak)
    tests/sim/       sim/: the mock autopilot and its clients, truth, sensors, feed, evaluation, demo
    tests/gcs/       groundstation/: `pmon gcs` verbs, hub, TAK, view, export
    tests/firmware/  against the real firmware's SITL (ArduPilot; PX4) and the mock's conformance to it
    tests/examples/  examples/, each script run as a user runs it
    tests/support/   helpers the tests share (imported as ``tests.support.NAME``); tests/data/ data
This file alone stays at the top. Fixtures every folder shares are in tests/conftest.py.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
PARTS = {"core", "app", "sim", "gcs", "firmware", "examples"}
PACKAGES = ("onboard", "sim", "groundstation", "bench")


def imported_names(path: Path) -> list[tuple[int, str]]:
    """(line, dotted name) of every import in a file, at any depth (a function's lazy import,
    and what is imported under ``if TYPE_CHECKING:`` for the annotations only, too); relative
    imports resolved against the file's package."""
    tree = ast.parse(path.read_text(), str(path))
    rel = path.relative_to(ROOT).with_suffix("").parts
    pkg = list(rel if path.name == "__init__.py" else rel[:-1])
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(pkg[:len(pkg) - node.level + 1] + ([base] if base else []))
            out += [(node.lineno, base)] + [(node.lineno, f"{base}.{a.name}") for a in node.names]
    return out


def test_no_test_module_imports_another():
    """Shared code is in tests/support/; a test module (or a helper, or a bench) that imports a
    test module or a conftest runs its tests' module-level code and couples their edits."""
    bad = []
    for path in [*TESTS.rglob("*.py"), *(ROOT / "bench").glob("*.py"), *(ROOT / "examples").glob("*.py")]:
        for line, name in imported_names(path):
            last = name.split(".")[-1]
            if name.split(".")[0] in ("conftest",) or last.startswith("test_") and (
                    name.startswith("tests.") or "." not in name):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)


def test_every_test_module_is_in_the_folder_of_its_part():
    loose = [p.name for p in TESTS.glob("test_*.py") if p != Path(__file__).resolve()]
    assert not loose, f"move into tests/<part>/ (this file's docstring says which): {loose}"
    folders = {p.parent.name for p in TESTS.rglob("test_*.py") if p.parent != TESTS}
    assert folders <= PARTS, f"test folders not in this file's docstring: {sorted(folders - PARTS)}"
    assert not list((TESTS / "support").glob("test_*.py")), "tests/support/ holds helpers, not tests"


def _module_graph() -> dict[str, set[str]]:
    """File-level import graph of the packages and bench/, every import at every depth: a
    function's lazy one, and one under ``if TYPE_CHECKING:`` too (two modules that need each
    other's names only for annotations still hold one role between them: the shared names go in
    a module of their own that both import)."""
    mods = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            parts = p.relative_to(ROOT).with_suffix("").parts
            mods[".".join(parts[:-1] if p.name == "__init__.py" else parts)] = p

    def owner(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None
    return {m: {t for _, n in imported_names(p) if (t := owner(n)) and t != m}
            for m, p in mods.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))
    for v in list(graph):
        if v not in index:
            visit(v)
    return out


def test_cycles_finds_a_cycle_and_only_cycles():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []


def test_an_annotation_only_import_closes_a_cycle(tmp_path, monkeypatch):
    """A module that takes another's names under ``if TYPE_CHECKING:`` still depends on it."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                           "    from pkg.b import B\n")
    (tmp_path / "pkg" / "b.py").write_text("from .a import A\n")
    monkeypatch.setitem(globals(), "ROOT", tmp_path)  # imported_names resolves against ROOT
    mods = ("pkg.a", "pkg.b")
    graph = {m: {t for t in mods if t != m and t in {n for _, n in imported_names(tmp_path / "pkg" / f"{m[-1]}.py")}}
             for m in mods}
    assert graph == {"pkg.a": {"pkg.b"}, "pkg.b": {"pkg.a"}}
    assert cycles(graph) == [["pkg.a", "pkg.b"]]


def test_onboard_imports_nothing_from_sim_or_groundstation():
    """onboard/ is what flies: not even a lazy import of the simulator or the ground station."""
    bad = [f"{m} imports {t}" for m, ts in _module_graph().items() if m.startswith("onboard")
           for t in ts if t.split(".")[0] != "onboard"]
    for p in (ROOT / "onboard").rglob("*.py"):  # tests/ too, which the graph leaves out
        bad += [f"{p.relative_to(ROOT)}:{line} imports {n}" for line, n in imported_names(p)
                if n.split(".")[0] in ("sim", "groundstation", "bench", "tests")]
    assert not bad, "\n".join(bad)


def test_no_import_cycle_between_files_or_packages():
    graph = _module_graph()
    assert cycles(graph) == []
    packages: dict[str, set[str]] = {}
    for m, ts in graph.items():
        packages.setdefault(m.split(".")[0], set()).update(t.split(".")[0] for t in ts)
    for p, ts in packages.items():
        ts.discard(p)
    assert cycles(packages) == [], packages


def test_tests_and_bench_do_not_import_each_other():
    """Both import the product (onboard/, groundstation/, sim/: the rig a bench and a test share),
    never each other: a test runs a bench as a program (``python -m bench.NAME``), and bench/ runs
    without sys.path edits."""
    benches = {p.stem for p in (ROOT / "bench").glob("*.py")} | {"bench"}
    bad = [f"{p.relative_to(ROOT)}:{line} imports {n}" for p in TESTS.rglob("*.py")
           for line, n in imported_names(p) if n.split(".")[0] in benches]
    for p in (ROOT / "bench").glob("*.py"):
        bad += [f"{p.relative_to(ROOT)}:{line} imports {n}" for line, n in imported_names(p)
                if n.split(".")[0] == "tests"]
        bad += [f"{p.relative_to(ROOT)}:{n.lineno} edits sys.path" for n in ast.walk(ast.parse(p.read_text()))
                if isinstance(n, ast.Attribute) and n.attr == "path" and ast.unparse(n.value) == "sys"]
    assert not bad, "\n".join(bad)


MAX_MODULE_LINES = 500  # past this a module usually holds two roles: split it by role (issue 43)
# modules allowed past MAX_MODULE_LINES, each with why; an entry back under the limit is removed
LONG_MODULES: dict[str, str] = {
}


def long_modules(limit: int = MAX_MODULE_LINES) -> list[tuple[str, int]]:
    """(path, lines) of every module of the packages and bench/ longer than ``limit`` lines."""
    out = []
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            n = len(p.read_text(encoding="utf-8").splitlines())
            if n > limit:
                out.append((p.relative_to(ROOT).as_posix(), n))
    return out


def test_no_module_is_longer_than_the_limit_but_the_allowed():
    """A module of onboard/, groundstation/, sim/ or bench/ holds one role in at most
    MAX_MODULE_LINES lines; LONG_MODULES names the few that may be longer, and why."""
    found = dict(long_modules())
    over = [f"{path}: {n} lines" for path, n in found.items() if path not in LONG_MODULES]
    assert not over, f"over {MAX_MODULE_LINES} lines (split by role, or allow in LONG_MODULES with why):\n" + "\n".join(over)
    stale = sorted(set(LONG_MODULES) - set(found))
    assert not stale, f"no longer over {MAX_MODULE_LINES} lines: remove from LONG_MODULES: {stale}"


MAX_FUNCTION_LINES = 60  # past this a function usually does two things: split it into named helpers (issue 43)
MAX_PARAMETERS = 8  # past this the arguments travel together: a frozen dataclass of them (issue 43)
SHAPED_PACKAGES = ("groundstation", "sim", "onboard", "bench")
# functions ("path:Class.name") allowed past MAX_FUNCTION_LINES, each with why; an entry back
# under the limit is removed
LONG_FUNCTIONS: dict[str, str] = {
}
# functions allowed more than MAX_PARAMETERS parameters (self/cls not counted), each with why; an
# entry back within the limit is removed
WIDE_SIGNATURES = {
    # a setting's declaration (onboard/settings/sections.py: one call per setting): its default, range,
    # unit and text, and its flags, each a keyword read where it is declared
    "onboard/settings/declare.py:number": "a number setting's default, range, unit, text and flags, by keyword",
    "onboard/settings/declare.py:integer": "an integer setting's default, range, unit, text and flags, by keyword",
    "onboard/settings/declare.py:vector": "a vector setting's default, length, range, unit, text and flags, by keyword",
    # ports of ArduPilot's AC_PosControl shaping functions: their argument lists are kept as the
    # C++ has them, so the port reads line by line against the reference
    "sim/mock/control_math.py:_shape_pos_vel_accel_xy": "AC_PosControl's shape_pos_vel_accel_xy: its arguments, "
                                                   "in its order",
    "sim/mock/control_math.py:_shape_z": "AC_PosControl's shape_pos_vel_accel for z: its arguments, in its order "
                                    "(the position as an error, the speed limits up and down)",
    # options each with its default, keyword-called by many: an options class would only wrap the
    # same keywords at every call, and the validated result is already one (EvalConfig; the mock)
    "sim/mock/autopilot.py:MockAutopilot.__init__": "the mock's options, each SITL's with its default (the class "
                                               "docstring), keyword-called by sim/stack/rig.py and two dozen tests",
    "sim/evaluation/config.py:make_config": "`pmon eval`'s options, keyword-called by some thirty callers",
    # not yet grouped (issue 43): each its own change
    "sim/stack/gcs_fake_vehicle.py:target_values": "PMON_TGT's fields with the tests' defaults, each varied by keyword",
    "sim/truth/world.py:TruthWorld.__init__": "the truth world's parts, put together by TruthWorld.from_scenario",
    "sim/mock/guided.py:fly_timeline": "a timeline of setpoints flown under the firmware's rate, timeout and limits",
    "onboard/app/kraken/source.py:KrakenSource.__init__": "the KrakenSDR section, the autopilot's clock, poses and UTC "
                                                   "map, and the callbacks into the app; built by KrakenInput, "
                                                   "bench/kraken.py and the tests' hand-fed source",
}


def function_shapes(packages=SHAPED_PACKAGES) -> list[tuple[str, int, int]]:
    """("path:Class.name", lines, parameters) of every function and method of ``packages``;
    parameters count every argument (``*args``, ``**kwargs`` and keyword-only too) but a
    method's self or cls."""
    out = []

    def visit(node, path: str, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = child.args
                n = (len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
                     + (a.vararg is not None) + (a.kwarg is not None))
                if a.args and a.args[0].arg in ("self", "cls"):
                    n -= 1
                name = prefix + child.name
                out.append((f"{path}:{name}", child.end_lineno - child.lineno + 1, n))
                visit(child, path, name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, path, prefix + child.name + ".")
            else:
                visit(child, path, prefix)
    for pkg in packages:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            visit(ast.parse(p.read_text(encoding="utf-8"), str(p)), p.relative_to(ROOT).as_posix(), "")
    return out


def test_no_function_is_longer_or_wider_than_the_limits_but_the_allowed():
    """A function of groundstation/, sim/, onboard/ or bench/ is at most MAX_FUNCTION_LINES lines
    and takes at most MAX_PARAMETERS parameters; LONG_FUNCTIONS and WIDE_SIGNATURES name the few
    that may not, and why."""
    shapes = function_shapes()
    long_ = {f: n for f, n, _ in shapes if n > MAX_FUNCTION_LINES}
    wide = {f: k for f, _, k in shapes if k > MAX_PARAMETERS}
    over = [f"{f}: {n} lines" for f, n in long_.items() if f not in LONG_FUNCTIONS]
    over += [f"{f}: {k} parameters" for f, k in wide.items() if f not in WIDE_SIGNATURES]
    assert not over, (f"over {MAX_FUNCTION_LINES} lines or {MAX_PARAMETERS} parameters (split into helpers, "
                      "group the parameters, or allow with why):\n" + "\n".join(over))
    stale = sorted((set(LONG_FUNCTIONS) - set(long_)) | (set(WIDE_SIGNATURES) - set(wide)))
    assert not stale, f"back within the limits: remove from LONG_FUNCTIONS/WIDE_SIGNATURES: {stale}"


def test_only_onboard_app_mavlink2_imports_mavutil():
    """pymavlink speaks MAVLink 1 unless MAVLINK20 is set before mavutil loads its dialect;
    onboard/app/mavlink2.py sets it, and every other module takes mavutil from there."""
    one = ROOT / "onboard" / "app" / "mavlink2.py"
    bad = [f"{p.relative_to(ROOT)}:{line}" for pkg in (*PACKAGES, "tests", "examples")
           for p in sorted((ROOT / pkg).rglob("*.py")) if p != one
           for line, n in imported_names(p) if n == "pymavlink.mavutil"]
    assert not bad, "import mavutil from onboard.app.mavlink2:\n" + "\n".join(bad)



LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", flags=re.M | re.S)


def _slug(heading: str) -> str:
    """The anchor GitHub gives a markdown heading: lower case, punctuation dropped, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(md: Path) -> set[str]:
    text = FENCE.sub("", md.read_text(encoding="utf-8"))
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6} +(.+?) *#*$", text, flags=re.M)}


def broken_links(md: Path) -> list[str]:
    """The relative links of a markdown file (``[text](target)``, images too) whose file, or
    heading anchor in a markdown file, does not exist; web and mail links are not checked."""
    text = re.sub(r"`[^`]*`", "", FENCE.sub("", md.read_text(encoding="utf-8")))
    bad = []
    for m in LINK.finditer(text):
        target = m.group(1)
        if re.match(r"[a-z][a-z0-9+.-]*:", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (md.parent / path).resolve() if path else md
        if not dest.exists():
            bad.append(f"{md.name}: {target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{md.name}: {target} (no such heading)")
    return bad


def test_broken_links_finds_a_missing_file_and_a_missing_heading(tmp_path):
    (tmp_path / "a.md").write_text("# A title: `x`\n\n[ok](#a-title-x) [gone](b.md) ![img](c.png) "
                                   "[no heading](a.md#nowhere) [web](https://example.com/x) `[code](d.md)`\n")
    assert broken_links(tmp_path / "a.md") == ["a.md: b.md (no such file)", "a.md: c.png (no such file)",
                                               "a.md: a.md#nowhere (no such heading)"]


def test_every_relative_link_of_the_readme_and_docs_resolves():
    """README.md's and docs/'s links to files and headings lead somewhere."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    assert [b for md in files for b in broken_links(md)] == []


def pmon_reads(path: Path, names: set[str], *, any_string: bool = False) -> list[tuple[int, str]]:
    """(line, name) of every subscript ``x["PMON_..."]`` of a parameter's name in a file;
    ``any_string``: of every string that is one (``params.get("PMON_PD")`` too)."""
    tree = ast.parse(path.read_text(), str(path))
    if any_string:
        return sorted((n.lineno, n.value) for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value in names)
    return [(n.lineno, n.slice.value) for n in ast.walk(tree)
            if isinstance(n, ast.Subscript) and isinstance(n.slice, ast.Constant) and n.slice.value in names]


def test_pmon_reads_finds_a_read_by_name(tmp_path):
    f = tmp_path / "m.py"
    f.write_text('budget = params["PMON_BUDGET"]\nok = params.settings.app.tick_budget_s\nd = {"PMON_PD": 1}\n'
                 'note = "PMON_PD is p_D"\n')
    assert pmon_reads(f, {"PMON_BUDGET", "PMON_PD"}) == [(1, "PMON_BUDGET")]
    assert pmon_reads(f, {"PMON_BUDGET", "PMON_PD"}, any_string=True) == [(1, "PMON_BUDGET"), (3, "PMON_PD")]


def test_no_setting_is_read_by_its_pmon_name_outside_the_parameter_table():
    """The product reads a parameter as its typed setting (``ParamTable.settings``), one name per
    quantity; its PMON name is the MAVLink edge's (onboard/app/params.py) and the declaration's
    (onboard/settings/sections.py): in onboard/, sim/ and groundstation/ no other string is one. Tests may
    read it by name, and the benches name one to the ground station's command line: they speak
    the protocol (a bench still never reads one by subscript)."""
    from onboard.settings.sections import PARAMS

    edge = {ROOT / "onboard" / "app" / "params.py", ROOT / "onboard" / "settings" / "sections.py"}
    found = [f"{p.relative_to(ROOT)}:{line}: {name}" for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))
             if p not in edge for line, name in pmon_reads(p, set(PARAMS), any_string=pkg != "bench")]
    assert not found, "read by PMON name outside the parameter table (use params.settings):\n" + "\n".join(found)


def _conftest_set(name: str) -> frozenset:
    """A frozenset({...}) of literals assigned in tests/conftest.py (read, not imported)."""
    tree = ast.parse((TESTS / "conftest.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and [t.id for t in node.targets if isinstance(t, ast.Name)] == [name]:
            return frozenset(ast.literal_eval(node.value.args[0]))
    raise AssertionError(f"tests/conftest.py has no {name}")


# what a compute-lane test must not do: wait on a clock, a thread, a socket or another process
_FLIGHT_NAMES = {"sleep", "socket", "threading", "Thread", "subprocess", "Popen", "MockAutopilot", "wait_for",
                 "distributed"}
_CLOCK_CALLS = {"monotonic", "time", "perf_counter"}


def _flies(fn: ast.FunctionDef) -> list[str]:
    names = [n.id if isinstance(n, ast.Name) else n.attr for n in ast.walk(fn)
             if isinstance(n, (ast.Name, ast.Attribute))]
    calls = [n.func.attr for n in ast.walk(fn) if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
             and isinstance(n.func.value, ast.Name) and n.func.value.id == "time"]
    return sorted({n for n in names if n in _FLIGHT_NAMES} | {f"time.{c}()" for c in calls if c in _CLOCK_CALLS})


def test_the_compute_lanes_tests_exist_and_wait_on_nothing():
    """tests/conftest.py's compute lane (tests/support/lanes.py) names existing modules and tests,
    and none of its test functions sleeps, reads a clock, or starts a thread, socket or process
    (those are the flights lane's: COMPUTE_MODULES_FLIGHTS)."""
    modules, flights = _conftest_set("COMPUTE_MODULES"), _conftest_set("COMPUTE_MODULES_FLIGHTS")
    assert not [m for m in modules if not (ROOT / m).is_file()], "COMPUTE_MODULES names a missing file"
    bad = []
    for m in sorted(modules):
        fns = [n for n in ast.parse((ROOT / m).read_text()).body if isinstance(n, ast.FunctionDef)]
        tests = {n.name: n for n in fns if n.name.startswith("test_")}
        helpers = {n.name for n in fns if not n.name.startswith("test_") and _flies(n)}  # one call deep
        for name, fn in tests.items():
            uses = _flies(fn) + sorted(helpers & {n.id for n in ast.walk(fn) if isinstance(n, ast.Name)})
            if f"{m}::{name}" not in flights and uses:
                bad.append(f"{m}::{name} uses {', '.join(uses)}")
        bad += [f"{f}: no such test in a compute module" for f in flights
                if f.split("::")[0] == m and f.split("::")[1] not in tests]
    bad += [f"{f}: its module is not in COMPUTE_MODULES" for f in flights if f.split("::")[0] not in modules]
    assert not bad, "\n".join(bad)


def test_the_lanes_exit_code_is_the_worse_lanes_and_a_lane_without_tests_fails_none():
    from tests.support.lanes import merged_exit

    assert merged_exit(0, 0) == 0 and merged_exit(0, 1) == 1 and merged_exit(1, 0) == 1
    assert merged_exit(5, 0) == 0 and merged_exit(0, 5) == 0 and merged_exit(5, 5) == 5
    assert merged_exit(2, 1) == 2 and merged_exit(5, 1) == 1


def _mock_of_names() -> list[tuple[str, str]]:
    """(the module marking it, the nodeid) of every ``@pytest.mark.mock_of(...)`` decorating a test under tests/."""
    found = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        fns = [n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.FunctionDef)]
        for node in (d for fn in fns for d in fn.decorator_list):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "mock_of"):
                found += [(str(path.relative_to(ROOT)), ast.literal_eval(a)) for a in node.args]
    return found


def test_every_mock_of_names_a_firmware_test_that_exists():
    """A stand-in names tests of tests/firmware/ that exist (a misspelt one would keep the mock's
    version running beside the real one, silently)."""
    names = _mock_of_names()
    assert len(names) >= 5, names
    bad = []
    for where, nodeid in names:
        module, _, name = nodeid.partition("::")
        path = ROOT / module
        if not module.startswith("tests/firmware/") or not path.is_file():
            bad.append(f"{where}: {nodeid}: not a module of tests/firmware/")
        elif name not in {n.name for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef)}:
            bad.append(f"{where}: {nodeid}: no such test")
    assert not bad, "\n".join(bad)


def test_a_stand_in_is_skipped_only_where_every_firmware_test_it_names_runs():
    import pytest

    from tests.support.stand_ins import stand_ins_covered

    class Item:
        def __init__(self, nodeid, *marks):
            self.nodeid, self.marks = nodeid, [m.mark for m in marks]

        def iter_markers(self, name):
            return (m for m in self.marks if m.name == name)

    fw_a, fw_b = "tests/firmware/test_x.py::test_a", "tests/firmware/test_x.py::test_b"
    mock = Item("tests/app/test_y.py::test_m", pytest.mark.mock_of(fw_a, fw_b))
    plain = Item("tests/app/test_y.py::test_plain")
    a, b = Item(fw_a), Item(fw_b)
    no_sitl = Item(fw_b, pytest.mark.skipif(True, reason="no SITL"))
    assert [i for i, _ in stand_ins_covered([mock, plain, a, b])] == [mock]
    assert fw_a in stand_ins_covered([mock, a, b])[0][1]
    assert stand_ins_covered([mock, plain, a]) == []  # one of them deselected (-m, -k, a path)
    assert stand_ins_covered([mock, a, no_sitl]) == []  # its firmware missing: skipped
    assert stand_ins_covered([mock, a, Item(fw_b, pytest.mark.skipif("sys.platform", reason="?"))]) == []
    assert stand_ins_covered([mock, a, Item(fw_b, pytest.mark.skip(reason="off"))]) == []
    assert [i for i, _ in stand_ins_covered([mock, a, Item(fw_b, pytest.mark.skipif(False, reason="-"))])] == [mock]
    assert stand_ins_covered([Item("t::m", pytest.mark.mock_of()), a]) == []  # names nothing: runs
