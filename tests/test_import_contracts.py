"""Layer contracts read from the source (AST), like the kernels' one in test_engine: the
daemon runs scenes and refuses unstable ones with the analysis, never with the benchmark
package (``hapsim.bench`` is charts and advice; its stability limits live in
``hapsim.analysis.integrators``)."""

from __future__ import annotations

from pathlib import Path

from test_engine import imported_modules  # same directory (pytest prepend import mode)

DAEMON_DIR = Path(__file__).resolve().parents[1] / "hapsim" / "daemon"


def _bench_imports(names: set[str]) -> set[str]:
    return {n for n in names if n == "hapsim.bench" or n.startswith("hapsim.bench.")}


def test_scanner_catches_bench_imports():
    """The scanner sees a daemon module importing hapsim.bench in any spelling."""
    for bad in ("from hapsim.bench.methods import stability_margin", "import hapsim.bench",
                "from ..bench import methods", "from ..bench.methods import oscillator_limits",
                "def f():\n    from hapsim.bench import capacity\n"):
        assert _bench_imports(imported_modules(bad, "hapsim.daemon.runner")), bad
    assert not _bench_imports(imported_modules(
        "from hapsim.analysis.integrators import stability_margin\nfrom . import loop",
        "hapsim.daemon.runner"))


def test_daemon_imports_nothing_from_bench():
    """Every module under hapsim/daemon/ (function-level imports included) keeps off
    hapsim.bench."""
    files = sorted(DAEMON_DIR.glob("*.py"))
    assert {f.name for f in files} >= {"__init__.py", "runner.py", "loop.py"}
    for f in files:
        module = "hapsim.daemon" + (".__init__" if f.stem == "__init__" else f".{f.stem}")
        bad = _bench_imports(imported_modules(f.read_text(), module))
        assert not bad, f"{f.name} imports hapsim.bench: {sorted(bad)}"


def test_old_bench_names_are_the_analysis_ones():
    """hapsim.bench.methods re-exports the moved module: one implementation, two names."""
    import hapsim.analysis.integrators as new
    import hapsim.bench.methods as old
    for name in new.__all__:
        assert getattr(old, name) is getattr(new, name), name
