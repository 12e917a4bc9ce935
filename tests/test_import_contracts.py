"""Layer contracts read from the source (AST), like the kernels' one in test_engine: the
daemon runs scenes and refuses unstable ones with the analysis, never with the benchmark
package (``hapsim.bench`` is charts and advice; its stability limits live in
``hapsim.analysis.integrators``)."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

from test_engine import imported_modules  # same directory (pytest prepend import mode)

#: pytest-xdist: the module's tests on one worker, so that the package's sources are parsed
#: once (:func:`_facts`) rather than by each test on each worker
pytestmark = pytest.mark.xdist_group("test_import_contracts")

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "hapsim"
#: The packages that run scenes and devices (both sides of the wire and the run's pipeline)
RUN_DIRS = tuple(PACKAGE_DIR / name for name in ("host", "emulated", "pipeline"))


def _bench_imports(names: set[str]) -> set[str]:
    return {n for n in names if n == "hapsim.bench" or n.startswith("hapsim.bench.")}


def test_scanner_catches_bench_imports():
    """The scanner sees a daemon module importing hapsim.bench in any spelling."""
    for bad in ("from hapsim.bench.methods import stability_margin", "import hapsim.bench",
                "from ..bench import methods", "from ..bench.methods import oscillator_limits",
                "def f():\n    from hapsim.bench import capacity\n"):
        assert _bench_imports(imported_modules(bad, "hapsim.pipeline.runner")), bad
    assert not _bench_imports(imported_modules(
        "from hapsim.analysis.integrators import stability_margin\nfrom . import loop",
        "hapsim.pipeline.runner"))


def test_run_packages_import_nothing_from_bench():
    """Every module under hapsim/host/, hapsim/emulated/ and hapsim/pipeline/
    (function-level imports included) keeps off hapsim.bench."""
    files = sorted(f for d in RUN_DIRS for f in d.glob("*.py"))
    assert {f.name for f in files} >= {"__init__.py", "runner.py", "loop.py", "mock.py"}
    for f in files:
        pkg = "hapsim." + f.parent.name
        module = pkg + (".__init__" if f.stem == "__init__" else f".{f.stem}")
        bad = _bench_imports(imported_modules(f.read_text(), module))
        assert not bad, f"{f.name} imports hapsim.bench: {sorted(bad)}"


def test_old_bench_names_are_the_analysis_ones():
    """hapsim.bench.methods re-exports the moved module: one implementation, two names."""
    import hapsim.analysis.integrators as new
    import hapsim.bench.methods as old
    for name in new.__all__:
        assert getattr(old, name) is getattr(new, name), name


# ----------------------------------------------------------------------------- the layers
# The house in floors, lowest first: a module imports only from its own floor or below
# (function-level imports included), and no modules import each other in a circle. A
# module of hapsim not named here stands on the top floor (nothing below may import it).
LAYERS = (
    # hapsim.applied: the account of the force a device applied per tick (plain arrays),
    # which the drivers' timing fills and the analysis and the daemon read;
    # hapsim.braking: the braking law after a stop on the motion (plain arrays), which the
    # 1-D host loop and the n-D drivers' loops (emulated and pipeline floors) share
    ("foundation", ("hapsim.errors", "hapsim.progress", "hapsim.blas", "hapsim.spawn",
                    "hapsim.kernels", "hapsim._yaml_lines", "hapsim.outputs",
                    "hapsim.applied", "hapsim.option_values", "hapsim.braking")),
    # the drivers' codecs (the bytes of other devices, as firmware_protocol is hapsim's):
    # a scene checks its device.protocol_options with them; their mocks stand higher, in
    # hapsim.emulated.driver_mock (outside the folder: nothing under hapsim/drivers/ stands above)
    ("scene", ("hapsim.scene_schema", "hapsim.scene_doc", "hapsim.drivers")),
    # the scene package stands with the models: its n-D reader takes a kinematic device's
    # Cartesian mass at its joints from the kinematics and hapsim.analysis.ths.matrix_loop
    ("models", ("hapsim.scene", "hapsim.device_file", "hapsim.engine", "hapsim.lockstep",
                "hapsim.lockstep_ports", "hapsim.joint_device",
                "hapsim.analysis", "hapsim.device_model", "hapsim.kinematics", "hapsim.plots",
                "hapsim.plots.bench", "hapsim.plots.family", "hapsim.plots.telemetry",
                "hapsim.plots.workspace", "hapsim.plots.zwidth")),
    # the device side of the wire: what pretends to be hardware (it never imports the
    # host's side: both share only the wire's codecs, hapsim.kernels.compiled_io and
    # firmware_protocol)
    ("emulated devices and sound", ("hapsim.emulated", "hapsim.audio")),
    # the host side of the wire: the loop, its compiled twin, its transport to a port
    ("host", ("hapsim.host",)),
    # the live view the run starts beside its loop: it reads the host's telemetry and the
    # audio controller; the run hands it its own measurement (hapsim.pipeline.measure)
    ("view", ("hapsim.view",)),
    # one run's pipeline
    ("pipeline", ("hapsim.pipeline",)),
    ("application", ("hapsim.bench", "hapsim.commands", "hapsim.cli", "hapsim.__main__",
                     "hapsim")),
)


def _modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its own name)."""
    out = {}
    for f in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = list(f.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


@functools.lru_cache(maxsize=None)
def _facts(path: Path) -> tuple:
    """What the tests read of one source file of the package, from one parse of it per
    worker (four tests walked every module's parse of their own: 1.0-1.4 CPU-s each, 5.3
    for the file in the suite): the modules it imports, its private imports, its reads
    of other objects' private state. The trees are not kept (400,000 nodes that every
    full collection of the worker would traverse)."""
    text = path.read_text()
    tree = ast.parse(text)
    parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
    own = ".".join(parts)               # a package as its __init__, as the scanners take it
    return (frozenset(imported_modules(text, own, tree)),
            tuple(_private_imports(text, own, tree)), tuple(_private_reads(text, tree)))


def _floor(module: str) -> int:
    """Index in :data:`LAYERS` of the longest prefix naming ``module``'s floor."""
    best, floor = -1, len(LAYERS) - 1
    for i, (_, names) in enumerate(LAYERS):
        for n in names:
            if (module == n or module.startswith(n + ".")) and len(n) > best:
                best, floor = len(n), i
    return floor


def _graph(sources: dict[str, str], imports=None) -> dict[str, set[str]]:
    """module -> the modules of ``sources`` it imports (a name resolved to the longest
    module it names: ``from hapsim.emulated.mock import MockDevice`` is hapsim.emulated.mock);
    ``imports``, when given, maps each module to what ``imported_modules`` found in it."""
    graph = {}
    for mod, text in sources.items():
        own = mod + ".__init__" if mod + ".__init__" in sources or _is_package(mod) else mod
        deps = set()
        names = imported_modules(text, own) if imports is None else set(imports[mod])
        # ``from hapsim import scene`` names the package and its module: the module counts
        names = {n for n in names if not any(m.startswith(n + ".") and m in sources
                                             for m in names)}
        for name in names:
            parts = name.split(".")
            for k in range(len(parts), 0, -1):
                target = ".".join(parts[:k])
                if target in sources:
                    if target != mod:
                        deps.add(target)
                    break
        graph[mod] = deps
    return graph


def _is_package(mod: str) -> bool:
    return (PACKAGE_DIR.parent / mod.replace(".", "/") / "__init__.py").exists()


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _upward(graph: dict[str, set[str]]) -> list[str]:
    return [f"{a} (floor {LAYERS[_floor(a)][0]}) imports {b} (floor {LAYERS[_floor(b)][0]})"
            for a in sorted(graph) for b in sorted(graph[a]) if _floor(b) > _floor(a)]


@functools.lru_cache(maxsize=1)
def _house_graph() -> dict[str, set[str]]:
    """The import graph of the package, read once per test session (the tests only read
    it)."""
    mods = _modules()
    return _graph({m: "" for m in mods}, {m: _facts(f)[0] for m, f in mods.items()})


def test_scanner_sees_circles_and_upward_imports():
    """The checks below can fail: a made-up pair importing each other is a circle, a
    scene module importing the analysis (even inside a function) is an upward import."""
    g = _graph({"hapsim.audio.a": "from hapsim.audio.b import x\n",
                "hapsim.audio.b": "def f():\n    from . import a\n",
                "hapsim.scene_schema": "def f():\n    import hapsim.analysis.loop as lp\n",
                "hapsim.errors": "from hapsim import scene_schema\n",
                "hapsim.analysis.loop": "from hapsim.scene_schema import KEYS\n"})
    assert ["hapsim.audio.a", "hapsim.audio.b"] in _circles(g)
    assert ["hapsim.analysis.loop", "hapsim.scene_schema"] in _circles(g)
    assert _upward(g) == ["hapsim.errors (floor foundation) imports hapsim.scene_schema (floor "
                          "scene)", "hapsim.scene_schema (floor scene) imports "
                          "hapsim.analysis.loop (floor models)"]
    assert _floor("hapsim.pipeline.runner") == 6 and _floor("hapsim.host.loop") == 4
    assert _floor("hapsim.emulated.mock") == 3 and _floor("hapsim.new_module") == 7


def test_no_module_imports_another_in_a_circle():
    """No circles of imports among hapsim's modules (function-level imports included)."""
    graph = _house_graph()
    assert {"hapsim.pipeline.runner", "hapsim.analysis.prediction"} <= set(graph)
    assert _circles(graph) == []


def test_no_arrow_joins_the_two_sides_of_the_wire():
    """The host side (hapsim.host) and the device side (hapsim.emulated) import nothing of
    each other, in either direction: they share only the wire's codecs, and the run
    (hapsim.pipeline) joins them (docs/design.md, 'The two sides of the wire')."""
    graph = _house_graph()
    sides = ("hapsim.host", "hapsim.emulated")

    def side(m):
        return next((s for s in sides if m == s or m.startswith(s + ".")), None)
    assert {side(m) for m in graph} >= set(sides)
    across = sorted(f"{a} -> {b}" for a in graph for b in graph[a]
                    if side(a) and side(b) and side(a) != side(b))
    assert across == []


def test_nothing_imports_upward():
    """Each module imports only from its floor or below (:data:`LAYERS`): the analysis and
    the device model never import the host, the drivers never the host, an emulated device
    never the host (the two sides of the wire share only its codecs), the scene never the
    analysis."""
    assert _upward(_house_graph()) == []


def _private_imports(text: str, module: str, tree=None) -> list[str]:
    """``from X import _name`` of another module (any depth; ``X`` resolved), as
    ``"X._name"``; a module's own names and dunders are not counted. ``tree``, when
    given, is ``ast.parse(text)`` already made."""
    package = module.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(text) if tree is None else tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            if stem == module:
                continue
            out += [f"{stem}.{a.name}" for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")]
    return out


def test_scanner_sees_private_imports():
    assert _private_imports("from hapsim.host.loop import HostLoop, _Lost\n",
                            "hapsim.host.fastloop") == ["hapsim.host.loop._Lost"]
    assert _private_imports("def f():\n    from .cordis import _clear\n",
                            "hapsim.kernels.audio") == ["hapsim.kernels.cordis._clear"]
    assert _private_imports("from hapsim.plots import pyplot as _plt\nfrom x import __all__\n",
                            "hapsim.plots.bench") == []


def test_no_module_imports_another_modules_private_names():
    """What one module takes from another has a public name (a shared helper is part of
    its module's interface: named, documented, tested as such)."""
    bad = {}
    for mod, f in _modules().items():
        found = list(_facts(f)[1])
        if found:
            bad[mod] = found
    assert bad == {}


# ------------------------------------------------------------------- the scene package
# hapsim.scene is six rooms in a row, each importing only the rooms before it: the
# elements (values, of every dimension), the rules (checks on the values), the model (Scene,
# checked by the rules when built; SceneND), the lines (where the reader is in a file, and
# the values it reads there), the devices (a 2-D or 3-D scene's device at its operating
# point), the reader (YAML with lines -> the model). Users import the package.
SCENE_ROOMS = ("hapsim.scene.elements", "hapsim.scene.rules", "hapsim.scene.model",
               "hapsim.scene.lines", "hapsim.scene.devices", "hapsim.scene.reader")
#: Modules outside the package that take a room directly, and which: a device file is a
#: scene's device section, read and checked by the same code, in the same line-numbered
#: context; the corrections take their table from the elements (through the package, the
#: analysis and the n-D device reader, which takes hapsim.analysis.ths.matrix_loop, would
#: import each other in a circle).
SCENE_ROOM_USERS = {"hapsim.device_file": {"hapsim.scene.lines", "hapsim.scene.reader",
                                           "hapsim.scene.rules"},
                    "hapsim.analysis.corrections": {"hapsim.scene.elements"}}


def test_the_scene_rooms_import_only_the_rooms_before_them():
    graph = _house_graph()
    assert set(SCENE_ROOMS) <= set(graph), "hapsim.scene lost a room"
    for i, room in enumerate(SCENE_ROOMS):
        inside = {m for m in graph[room] if m == "hapsim.scene" or m.startswith("hapsim.scene.")}
        assert inside <= set(SCENE_ROOMS[:i]), f"{room} imports {sorted(inside)}"


def test_only_the_device_room_reaches_the_models_and_only_inside_its_functions():
    """The scene package stands on the models floor for one room: the device reader of a
    2-D or 3-D scene (hapsim.scene.devices) takes a kinematic device's Cartesian mass at its
    joints from hapsim.kinematics and hapsim.analysis.ths.matrix_loop (the loop room of
    the THS package, not the package: its render reaches the scene), inside its functions.
    Every other room imports from the scene floor or below, and importing the package loads
    neither the kinematics nor the analysis (a subprocess, from a fresh interpreter)."""
    import subprocess
    import sys
    graph = _house_graph()
    scene_floor = _floor("hapsim.scene_schema")
    above = {}
    for room in SCENE_ROOMS:
        found = {d for d in graph[room] if _floor(d) > scene_floor
                 and not (d == "hapsim.scene" or d.startswith("hapsim.scene."))}
        if found:
            above[room] = found
    assert above == {"hapsim.scene.devices": {"hapsim.kinematics",
                                              "hapsim.analysis.ths.matrix_loop"}}
    tree = ast.parse((PACKAGE_DIR / "scene" / "devices.py").read_text())
    top = "\n".join(ast.unparse(n) for n in tree.body
                    if isinstance(n, (ast.Import, ast.ImportFrom)))
    assert not {d for d in imported_modules(top, "hapsim.scene.devices")
                if d.startswith(("hapsim.kinematics", "hapsim.analysis"))}
    code = ("import sys, hapsim.scene; print(sorted(m for m in sys.modules "
            "if m.startswith(('hapsim.kinematics', 'hapsim.analysis'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=PACKAGE_DIR.parent).stdout
    assert out.strip() == "[]"


def test_outside_the_scene_package_only_the_named_users_take_a_room():
    graph = _house_graph()
    found = {}
    for mod, deps in graph.items():
        if mod == "hapsim.scene" or mod.startswith("hapsim.scene."):
            continue
        rooms = {d for d in deps if d in SCENE_ROOMS}
        if rooms:
            found[mod] = rooms
    assert found == SCENE_ROOM_USERS


def test_the_scene_package_keeps_its_public_names():
    """``from hapsim.scene import ...`` is what it was before the package: every name of
    its ``__all__`` is there, and the classes say they are the package's rooms'."""
    import hapsim.scene as sc
    assert set(sc.__all__) >= {"Mass", "Link", "Device", "Hand", "CORRECTIONS", "Impulse",
                               "Excitation", "Safety", "Listen", "Audio", "Scene",
                               "load_scene", "parse_scene", "audio_substeps", "PROTOCOLS"}
    for name in sc.__all__:
        assert hasattr(sc, name), name
    assert sc.Scene.__module__ == "hapsim.scene.model"


def _folder_upward(graph: dict[str, set[str]], floor=None) -> list[str]:
    """Imports into a folder (a sub-package of hapsim) that holds a module standing above
    the importer: read folder by folder, such an import climbs even when the module taken
    stands low (the scene importing the drivers' codecs while the drivers' mocks shared
    their folder). ``floor``: module -> index in :data:`LAYERS` (default :func:`_floor`)."""
    floor = floor or _floor
    folders: dict[str, int] = {}
    for mod in graph:
        parts = mod.split(".")
        for k in range(2, len(parts)):
            folder = ".".join(parts[:k])
            folders[folder] = max(folders.get(folder, -1), floor(mod))
        if _is_package(mod):
            folders[mod] = max(folders.get(mod, -1), floor(mod))
    out = []
    for a in sorted(graph):
        for b in sorted(graph[a]):
            parts = b.split(".")
            for k in range(2, len(parts) + 1):
                folder = ".".join(parts[:k])
                if folder in folders and not (a == folder or a.startswith(folder + ".")) \
                        and folders[folder] > floor(a):
                    out.append(f"{a} (floor {LAYERS[floor(a)][0]}) imports {b} of folder "
                               f"{folder}, which holds floor {LAYERS[folders[folder]][0]}")
                    break
    return out


def test_scanner_sees_an_upward_folder():
    """The house before the mocks left the drivers' folder: module by module nothing
    climbed, folder by folder the scene climbed to the devices floor."""
    g = _graph({"hapsim.scene": "def f():\n    from hapsim.drivers import get_driver\n",
                "hapsim.drivers": "", "hapsim.drivers.mock": "",
                "hapsim.audio": "", "hapsim.audio.live": ""})

    def floor(mod):                   # the layers as they were: the mocks on devices,
        if mod.startswith("hapsim.drivers.mock"):     # the scene package on the scene floor
            return 3
        return 1 if mod == "hapsim.scene" else _floor(mod)
    assert _upward(g) == []
    assert _folder_upward(g, floor) == ["hapsim.scene (floor scene) imports hapsim.drivers of folder "
                                 "hapsim.drivers, which holds floor emulated devices and sound"]


def test_nothing_imports_into_a_folder_that_stands_above_it():
    """Read folder by folder, the house has no upward arrow either: the drivers' folder
    holds the codecs and the driver transport (scene floor); their byte-exact mocks stand
    in hapsim.emulated.driver_mock (the emulated devices' floor)."""
    assert _folder_upward(_house_graph()) == []


def test_no_module_reads_an_engines_private_state():
    """The live sound and the contact replay read an Engine through its public accessors
    (``kernel_pack``, ``multirate_pack``, ``port_index``, ``positions``, ``corrected``),
    not its ``_x``/``_xp``/``_multi``/``_port``: a name bound to an engine, read with a
    leading underscore, appears nowhere outside the engine and its subclass in
    hapsim.host.correction."""
    import re
    pattern = re.compile(r"\b(?:eng|engine|self\.eng|self\.engine)\._[a-z]\w*")
    assert pattern.search("before = eng._x[self.uniq].copy()")
    assert not pattern.search("x = self._x; y = eng.positions")
    bad = {}
    for mod, f in _modules().items():
        if mod == "hapsim.engine" or mod.startswith("hapsim.engine."):
            continue
        found = pattern.findall(f.read_text())
        if found:
            bad[mod] = sorted(set(found))
    assert bad == {}


# ------------------------------------------------------- other objects' private state
def _private_reads(text: str, tree=None) -> list[str]:
    """Reads and writes of another object's ``_name`` (``obj._x``, ``getattr(obj,
    "_x")``, ``hasattr``/``setattr`` alike), as ``"obj._x"`` with ``obj`` as written.

    Not counted: ``self``/``cls``/``super()`` (an object's own and inherited state),
    dunders, and a name this module's own classes define (``self._x = ...`` or a ``_x``
    in a class body: another instance of the module's class, read by its own code).
    ``tree``, when given, is ``ast.parse(text)`` already made."""
    tree = ast.parse(text) if tree is None else tree
    own = set()
    for n in ast.walk(tree):
        if (isinstance(n, ast.Attribute) and not isinstance(n.ctx, ast.Load)
                and isinstance(n.value, ast.Name) and n.value.id in ("self", "cls")):
            own.add(n.attr)
        elif isinstance(n, ast.ClassDef):
            for b in n.body:
                if isinstance(b, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    own.add(b.name)
                elif isinstance(b, (ast.Assign, ast.AnnAssign)):
                    for t in (b.targets if isinstance(b, ast.Assign) else [b.target]):
                        if isinstance(t, ast.Name):
                            own.add(t.id)
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Attribute):
            name, value = n.attr, n.value
        elif (isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
              and n.func.id in ("getattr", "hasattr", "setattr", "delattr")
              and len(n.args) >= 2 and isinstance(n.args[1], ast.Constant)
              and isinstance(n.args[1].value, str)):
            name, value = n.args[1].value, n.args[0]
        else:
            continue
        if not name.startswith("_") or (name.startswith("__") and name.endswith("__")):
            continue
        if isinstance(value, ast.Name) and value.id in ("self", "cls"):
            continue
        if (isinstance(value, ast.Call) and isinstance(value.func, ast.Name)
                and value.func.id == "super"):
            continue
        if name not in own:
            out.append(f"{ast.unparse(value)}.{name}")
    return out


#: Documented functions of the standard library whose names begin with an underscore.
PUBLIC_UNDERSCORE = {"os._exit", "sys._getframe"}
#: Private reads that stay, each with its reason: (module, "obj._name") -> why.
PRIVATE_READS_ALLOWED = {
    **{("hapsim.audio.jack_native", r): "JACK-Client exposes neither libjack's path nor the "
       "C pointers (cffi) the native callback is registered with"
       for r in ("jack._libname", "jack._ffi", "client._ptr")},
    **{("hapsim.audio.live", r): "jack_set_process_callback with a numba cfunc needs "
       "JACK-Client's cffi handle and the client's and ports' C pointers, which it does "
       "not expose" for r in ("jack._ffi", "jack._lib", "self.client._ptr", "p._ptr")},
    **{("hapsim.audio.jack_client", r): "unsetting the xrun and buffer-size callbacks "
       "(jack_set_xrun_callback(client, NULL, NULL)) needs JACK-Client's cffi handle and "
       "the client's C pointer: JACK-Client has no call that unsets a callback"
       for r in ("jack._ffi", "jack._lib", "client._ptr")},
    ("hapsim.cli", "argparse._SubParsersAction"): "argparse has no public type or list of a "
    "parser's sub-commands and options (its error() finds the chosen sub-command's)",
    ("hapsim.cli", "parser._actions"): "argparse: a parser's options have no public list",
    **{("hapsim.commands.run", r): "argparse: a parser's options have no public list (run "
       "--help shows the common ones, --help-all every one)" for r in ("parser._actions",
                                                                        "p._actions")},
    ("hapsim.option_values", "parser._actions"): "argparse: a parser's options have no "
    "public list (check_numbers checks the declared ranges of a sub-command's options)",
    ("hapsim.__main__", "hapsim._quiet_interrupt_at_start"): "the package's own start-up, "
    "run by its own entry point before any import (not an API)",
    # The compiled mock hands MockDevice's state over and back. What is left: MockDevice gets a
    # public hand-over (its sequence, status, last force time, applied force, command and
    # delay ring), and serve_fd/compiled_reason read MockPhysics.noisy/.state_space,
    # StreamDecoder.overflow and a public "bytes queued" of FaultyDevice.
    **{("hapsim.emulated.fastmock", f"mock.{a}"): "MockDevice's state hand-over (it needs a "
       "public one)" for a in ("_applied", "_applied_seq",
                                                   "_last_force_us", "_plant_us", "_rf",
                                                   "_rs", "_status_extra", "_u")},
    **{("hapsim.emulated.serve", r): "switch to public names (ph.noisy, ph.state_space, "
       "dev.decoder.overflow; FaultyDevice needs one)"
       for r in ("ph._rng", "ph._grip", "dev.decoder._overflow", "dev._out")},
}


def test_scanner_sees_private_reads():
    found = _private_reads(
        "def f(run, dec, o):\n"
        "    a = run.loop._t0\n    b = getattr(run.loop, '_t0', None)\n"
        "    dec._buf = b''\n    o.__dict__\n    hasattr(o, '_x')\n")
    assert sorted(found) == ["dec._buf", "o._x", "run.loop._t0", "run.loop._t0"]
    assert _private_reads(
        "class A:\n    _n = 0\n    def __init__(self):\n        self._x = 1\n"
        "    def __eq__(self, other):\n        return self._x == other._x and other._n\n"
        "    def g(self):\n        return super()._y + self._z + type(self)._n\n") == []
    assert _private_reads("class A:\n    def g(self, o):\n        o._x = 1\n") == ["o._x"]


def test_no_module_reads_another_objects_private_state():
    """An object's ``_name`` is read and written by its own class (and the module that
    defines it) only: what another module needs has a public, documented name
    (``Engine.kernel_pack``, ``LiveSound.callback_pack``, ``StreamDecoder.take_partial``,
    ``HostLoop.armed_at`` ...). The few reads of other libraries' internals that stay
    are listed with their reason, and an entry no longer needed is an error too."""
    seen, bad = set(), {}
    for mod, f in _modules().items():
        for r in _facts(f)[2]:
            if r in PUBLIC_UNDERSCORE:
                continue
            if (mod, r) in PRIVATE_READS_ALLOWED:
                seen.add((mod, r))
            else:
                bad.setdefault(mod, set()).add(r)
    assert bad == {}
    assert set(PRIVATE_READS_ALLOWED) - seen == set()


# --------------------------------------------------------------------- the THS package
#: hapsim.analysis.ths, the THS of every dimension, is four rooms in a row, each importing
#: only the rooms before it: the loop with matrices, the hold and delay as matrices (state
#: matrix, poles), the felt matrices, render and calibrate
#: (docs/design.md, 'Package layout'). The scene's device reader takes the first room alone.
THS_ROOMS = ("hapsim.analysis.ths.matrix_loop", "hapsim.analysis.ths.holds",
             "hapsim.analysis.ths.felt", "hapsim.analysis.ths.render")


def test_the_ths_rooms_import_only_the_rooms_before_them():
    """No module named ``*_nd`` in the analysis (issue 30: one THS for every dimension),
    and the THS package's rooms stand in their row; the first imports nothing of the
    analysis but the 1-D loop and the split hold's delay."""
    graph = _house_graph()
    assert not [m for m in graph if m.startswith("hapsim.analysis.") and m.endswith("_nd")]
    assert set(THS_ROOMS) <= set(graph), "hapsim.analysis.ths lost a room"
    for i, room in enumerate(THS_ROOMS):
        inside = {m for m in graph[room] if m.startswith("hapsim.analysis.ths")}
        assert inside <= set(THS_ROOMS[:i]), f"{room} imports {sorted(inside)}"
    assert {m for m in graph[THS_ROOMS[0]] if m.startswith("hapsim.analysis")} == \
        {"hapsim.analysis.loop", "hapsim.analysis.subsample"}
