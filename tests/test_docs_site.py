"""The documentation: the MkDocs site builds with warnings as errors, its measured figures
come from the tools' files, and the command examples marked for the tests do what they show.

Markers (an HTML comment on the line just above a fenced block, in README.md or docs/*.md):

``<!-- test: output -->`` above a ```` ```console ```` block
    every ``$ hapsim ...`` line is run (in this process, ``hapsim.cli.main``) and must exit
    0 and print exactly the lines that follow it, up to the next ``$`` line;
``<!-- test: run -->`` above a ```` ```sh ```` block
    every line (comments after ``#`` dropped) is a ``hapsim`` command that must exit 0.

Only cheap commands are marked (each well under a second once imported): a run, a chart or
a benchmark is shown unmarked.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

from from_file import load_module  # same directory
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = [ROOT / "README.md"] + sorted(DOCS.glob("*.md"))
BLOCK = re.compile(r"^<!-- test: (run|output) -->\n```(sh|console)\n(.*?)^```", re.M | re.S)


def _macros():
    return load_module(ROOT / "tools" / "docs_macros.py")


def _blocks(kind: str) -> list:
    out = []
    for page in PAGES:
        for m in BLOCK.finditer(page.read_text()):
            assert (m.group(1), m.group(2)) in (("run", "sh"), ("output", "console")), (
                f"{page.name}: marker 'test: {m.group(1)}' above a {m.group(2)} block")
            if m.group(1) == kind:
                line = page.read_text()[:m.start()].count("\n") + 1
                out.append(pytest.param(m.group(3), id=f"{page.name}:{line}"))
    return out


def _hapsim(argv: list[str], capsys) -> tuple[int, str]:
    from hapsim.cli import main
    capsys.readouterr()
    code = main(argv)
    return code, capsys.readouterr().out


@pytest.fixture
def in_scratch(tmp_path, monkeypatch):
    """A scratch working directory where ``configs/`` is the repository's."""
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_site_builds_with_warnings_as_errors(tmp_path):
    """``mkdocs build --strict``: no broken link, no page outside the nav, no macro whose
    file or field is missing; the built pages hold the figures of the tools' files."""
    pytest.importorskip("mkdocs", reason="mkdocs is in the test extra: pip install -e '.[test]'")
    site = tmp_path / "site"
    p = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                        "--config-file", str(ROOT / "mkdocs.yml"), "--site-dir", str(site)],
                       capture_output=True, text=True, cwd=str(ROOT), timeout=300)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert "WARNING" not in p.stderr, p.stderr[-3000:]
    # never silent for seconds (issue 31): a build longer than two of the hook's progress
    # intervals (tools/docs_macros.PROGRESS_S) has said how far it is at least once
    took = float(re.search(r"Documentation built in ([0-9.]+) seconds", p.stderr).group(1))
    if took > 2 * 0.5:
        assert re.search(r"hapsim docs: \d+ of \d+ pages (read|written)", p.stderr), p.stderr
    soak = json.loads((DOCS / "soak.json").read_text())
    page = (site / "reliability" / "index.html").read_text()
    assert f"{soak['lost']} / {soak['recovered']}" in page
    assert "{{" not in page
    loss = json.loads((DOCS / "driver_loss.json").read_text())
    page = (site / "drivers" / "index.html").read_text()
    for drv, s in loss["summary"].items():     # the page's counts are the file's
        assert f"{s['within']} of {s['runs']} within" in page, drv
    for r in loss["runs"]:                      # and each run is in its table
        assert r["k_rel"] is None or f"{100 * r['k_rel']:+.3f} %" in page, r
    assert "{{" not in page


def test_marked_blocks_exist_on_the_pages_a_user_reads_first():
    """The README's check and calibrate examples, and the analysis page's, are tested."""
    ids = [p.id for p in _blocks("output")]
    assert any(i.startswith("README.md:") for i in ids), ids
    assert any(i.startswith("stability.md:") for i in ids), ids


@pytest.mark.parametrize("block", _blocks("output"))
def test_console_example_prints_what_the_page_shows(block, in_scratch, capsys):
    runs = re.split(r"^\$ ", block, flags=re.M)[1:]
    assert runs, "an output block without a '$ ' command"
    for run in runs:
        cmd, _, shown = run.partition("\n")
        argv = shlex.split(cmd.split("  #")[0])
        assert argv[0] == "hapsim", cmd
        code, out = _hapsim(argv[1:], capsys)
        assert code == 0, (cmd, out)
        assert [ln.rstrip() for ln in out.rstrip("\n").splitlines()] == \
            [ln.rstrip() for ln in shown.rstrip("\n").splitlines()], cmd


@pytest.mark.parametrize("block", _blocks("run"))
def test_shell_example_runs(block, in_scratch, capsys):
    lines = [ln.split("#")[0].strip() for ln in block.splitlines()]
    lines = [ln for ln in lines if ln]
    assert lines
    for ln in lines:
        argv = shlex.split(ln)
        assert argv[0] == "hapsim", f"only hapsim commands are run from the docs: {ln}"
        code, out = _hapsim(argv[1:], capsys)
        assert code == 0, (ln, out)


def test_macros_quote_the_files_and_fail_on_what_is_missing(tmp_path):
    """value / table / include read the file; a missing field or file is an error naming
    the macro, never an empty cell."""
    m = _macros()
    (tmp_path / "r.json").write_text(json.dumps(
        {"rows": [{"n": 10, "a": 1.5, "b": 3.0, "ok": True},
                  {"n": 20, "a": 2.0, "b": None, "ok": False}],
         "by": {"1000.0": {"x": {"late": 5, "ticks": 200}}}, "rx.drop": 7}))
    (tmp_path / "t.md").write_text("| a |\n|---|\n| 1 |\n")
    text = ('v={{ value "r.json" "rows.1.a" ".2f" }} d={{ value "r.json" "rx\\.drop" }}\n'
            '{{ table "r.json" "rows" "n=n" "ratio=a/b:.3f" "ok=ok" }}\n'
            '{{ table "r.json" "by" "rate=@key" "late=x.late/x.ticks:.1f%" }}\n'
            '{{ include "t.md" }}')
    got = m.expand(text, tmp_path)
    assert got.splitlines() == [
        "v=2.00 d=7",
        "| n | ratio | ok |", "|---|---|---|", "| 10 | 0.500 | yes |", "| 20 | - | no |",
        "| rate | late |", "|---|---|", "| 1000.0 | 2.5 % |",
        "| a |", "|---|", "| 1 |"]
    for bad in ('{{ value "r.json" "rows.5.a" }}', '{{ value "r.json" "nope" }}',
                '{{ table "r.json" "rows" "x=missing" }}', '{{ include "none.md" }}',
                '{{ value "none.json" "a" }}'):
        with pytest.raises(m.MacroError, match=re.escape(bad)):
            m.expand(bad, tmp_path)


def test_table1_file_is_what_the_analysis_computes_now():
    """docs/table1_table.md (written by tools/make_figures.py, included by docs/table1.md)
    is the paper's Table 1 as ``table1_experiment`` computes it today."""
    from hapsim.analysis.table1 import table1_experiment, table1_markdown
    assert (DOCS / "table1_table.md").read_text() == \
        table1_markdown(table1_experiment()).rstrip("\n") + "\n"


def test_readme_is_short_and_names_the_shipped_scenes_that_exist():
    """The README stays a first-ten-minutes page; its table of shipped scenes names every
    file of configs/ and nothing else."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    sec = text[text.index("## Shipped scenes"):]
    sec = sec[:sec.index("\n## ", 1)]
    listed = set(re.findall(r"^\| `configs/([^`]+)`", sec, re.M))
    assert listed == set(os.listdir(ROOT / "configs")), listed
    for name in set(re.findall(r"configs/([\w.-]+\.(?:yaml|csv))", text)):
        assert (ROOT / "configs" / name).exists(), name


def test_readme_links_lead_to_pages_of_the_site():
    """Every docs/ link of the README names a page in mkdocs.yml's nav."""
    text = (ROOT / "README.md").read_text()
    nav = (ROOT / "mkdocs.yml").read_text()
    for page in set(re.findall(r"\]\(docs/([\w-]+\.md)", text)):
        assert (DOCS / page).exists() and f" {page}" in nav, page


# an old citation of the unshipped design notes: "DESIGN" then a section sign or "Sec.", or
# their path under shared/ (spelled with escapes so that this file does not match itself)
STALE_CITATION = "DESIGN(\\.md)?\\s*(\u00a7|Sec\\.)|shared/DESIG[N]"


def test_design_citations_name_sections_that_exist():
    """The source cites the design by docs/design.md's section titles ("docs/design.md,
    'The inverse map'"), never by the section numbers of the unshipped design notes; every
    title cited is a heading of docs/design.md."""
    heads = set(re.findall(r"^#{2,3} (.+)$", (DOCS / "design.md").read_text(), re.M))
    cited, stale = set(), []
    for folder in ("hapsim", "tests", "tools", "firmware_protocol", "docs"):
        for path in (ROOT / folder).rglob("*"):
            if path.suffix not in (".py", ".md", ".c", ".h") or path.name == "test_docs_site.py":
                continue
            text = path.read_text(errors="replace")
            if re.search(STALE_CITATION, text):
                stale.append(str(path.relative_to(ROOT)))
            # a citation, possibly wrapped: docs/design.md, 'A' (and 'B')
            for m in re.finditer(r"docs/design\.md,\s+((?:'[^']+'(?:\s*(?:,|and)\s*)?)+)",
                                 text):
                cited.update(re.findall(r"'([^']+)'", m.group(1)))
    assert not stale, stale
    assert cited and cited <= heads, sorted(cited - heads)


def test_readme_commands_table_is_the_cli():
    """The README's commands table lists every subcommand ``hapsim --help`` offers, and
    nothing else (``kinematics`` was missing from it)."""
    from hapsim.cli import build_parser
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    text = (ROOT / "README.md").read_text()
    sec = text[text.index("## Commands"):]
    sec = sec[:sec.index("\n## ", 1)]
    listed = set(re.findall(r"^\| `hapsim ([\w-]+)", sec, re.M))
    assert listed == set(sub.choices), sorted(listed ^ set(sub.choices))
