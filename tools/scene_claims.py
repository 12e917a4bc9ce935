"""What each shipped scene says it will state, and what its run states (issue 31 item 4).

For every ``configs/*.yaml``: ``hapsim check SCENE --json`` (its verdict), ``hapsim run
SCENE --json`` (the embedded mock, or the scene's own driver's emulated board, in real
time, default duration) with what it said on stderr before its loop (``predicted before
the run`` / ``said before the run``) and the verdict it states; for the delta scenes also
``hapsim run SCENE --driver falcon --firmware FILE --packets 200 --json`` (the emulated
Falcon; a random image: the emulated loader takes any), for the pantograph scenes
``hapsim run SCENE --driver haply --json`` (the emulated 2DIY in real time). A row agrees when the run
states what was predicted: a statement before the run and a "not measurable" (or "not
measured") run, or no statement and a run that states "within" (or "partly within"
with what it did not state named before); a scene without a port is refused by both
(exit 2; ``check`` reports its modes). Prints the Markdown table of docs/testing.md, 'What each shipped scene
states'.

    python tools/scene_claims.py [--only NAME ...] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _hapsim(args, timeout=600):
    """Run ``hapsim ARGS`` in a child: (exit code, stdout's JSON or None, stderr, s)."""
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "hapsim", *args], cwd=ROOT, text=True,
                       capture_output=True, timeout=timeout)
    try:
        out = json.loads(p.stdout) if p.stdout.strip() else None
    except ValueError:
        out = None
    return p.returncode, out, p.stderr, time.monotonic() - t0


def _reason(out) -> str | None:
    """The run's reason for its verdict (the felt pair's, the matrices', the Falcon's)."""
    if not isinstance(out, dict):
        return None
    if "felt_matrices" in out:
        return out["felt_matrices"].get("reason")
    m = out.get("measured")
    return out.get("reason") or (m.get("reason") if isinstance(m, dict) else None)


def _said(err: str) -> str | None:
    """What the run said on stderr before its loop (None: nothing)."""
    for line in err.splitlines():
        if "predicted before the run" in line or "said before the run" in line:
            return line
    return None


def _states(rc: int, out) -> str:
    """The run's verdict of what it measured (the felt pair, matrices, or the Falcon's)."""
    if out is None:
        return f"no report (exit {rc})"
    if "error" in out and "exit" in out:
        return "refused"
    if "felt_matrices" in out:                       # --driver falcon
        return out["felt_matrices"]["verdict"]
    return str(out.get("verdict"))


def _agrees(portless: bool, said, states: str) -> bool:
    if portless:                                     # check reports; nothing to run
        return states == "refused"
    if said is not None:
        if "partly measurable" in said:
            return states in ("partly within", "not measurable")
        return states in ("not measurable", "not measured")
    return states in ("within",)


def claims(paths, firmware: str) -> list:
    """One row per run: scene, command, check's verdict, what was said before the run,
    what the run states, whether they agree, the run's exit code and wall time [s]."""
    rows = []
    for path in paths:
        rel = os.path.relpath(path, ROOT)
        rc_c, chk, _, _ = _hapsim(["check", rel, "--json"])
        portless = "kind: port" not in Path(path).read_text()
        check = chk.get("verdict") if isinstance(chk, dict) and "verdict" in chk else (
            f"refused (exit {rc_c})")
        if portless:
            check += ", no port"
        runs = [["run", rel, "--json"]]
        if "kind: delta" in Path(path).read_text():
            runs.append(["run", rel, "--driver", "falcon", "--firmware", firmware,
                         "--packets", "200", "--json"])
        if "kind: pantograph" in Path(path).read_text():
            runs.append(["run", rel, "--driver", "haply", "--json"])
        for argv in runs:
            rc, out, err, s = _hapsim(argv)
            said = _said(err)
            states = _states(rc, out)
            rows.append({"scene": rel, "command": "hapsim " + " ".join(
                a if a != firmware else "FILE" for a in argv), "check": check,
                "said_before_run": said, "states": states, "reason": _reason(out),
                "agrees": _agrees(portless, said, states), "exit": rc,
                "seconds": round(s, 1)})
            print(f"{rel}: {states} ({'agrees' if rows[-1]['agrees'] else 'DISAGREES'})",
                  file=sys.stderr, flush=True)
    return rows


def table(rows) -> str:
    """The Markdown table of docs/testing.md."""
    out = ["| scene | run | `check` | said before the run | the run states | agrees |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        said = r["said_before_run"]
        if said:                 # "hapsim run: SCENE: WHAT, predicted before the run (...)"
            said = said.split(": ", 2)[2].split(", predicted before")[0].split(
                ", said before")[0]
        run = ("`--driver falcon`" if "--driver falcon" in r["command"] else
               "`--driver haply`" if "--driver haply" in r["command"] else "`run`")
        out.append(f"| `{Path(r['scene']).name}` | {run} | {r['check']} | {said or '-'} | "
                   f"{r['states']} (exit {r['exit']}) | {'yes' if r['agrees'] else 'NO'} |")
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="scene names (without .yaml)")
    ap.add_argument("--json", help="write the rows as JSON here")
    a = ap.parse_args()
    paths = sorted((ROOT / "configs").glob("*.yaml"))
    if a.only:
        paths = [p for p in paths if p.stem in a.only]
    with tempfile.TemporaryDirectory() as tmp:
        fw = os.path.join(tmp, "falcon.bin")
        with open(fw, "wb") as fh:
            fh.write(os.urandom(1000))
        rows = claims(paths, fw)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    print(table(rows))
    return 0 if all(r["agrees"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
