"""Faust ``mi.lib`` twin of a hapsim scene: program generator, C++ driver and build helpers.

Used by ``tests/test_faust_oracle.py`` (Faust as a correctness oracle) and by
``tools/bench_engine.py`` (Faust as a speed peer). Everything is written into a caller-given
temporary directory; nothing touches the repository.

Parameter mapping hapsim -> Faust 2.54 ``mi.lib`` (read from ``/usr/share/faust/mi.lib``)
-------------------------------------------------------------------------------------------
``mi.lib`` is sample-rate normalised: its mass update is
``x[n+1] = 2 x[n] - x[n-1] + F / m_f`` and its links output ``k_f dx + z_f d(dx)``. With
``T = 1 / rate_hz`` the hapsim scheme (docs/design.md, 'The scheme') is reproduced exactly by

* mass ``m`` [kg]          -> ``mi.mass(m / T^2, 0, x0, x1_f)``;
* stiffness ``K`` [N/m]    -> ``k_f = K`` (forces stay in newtons);
* damping ``B`` [N s/m]    -> ``z_f = B / T`` (hapsim's own per-sample ``z``);
* contact threshold        -> ``mi.collision(K, B/T, thr, ...)`` (same sign convention:
  spring ``K (x1 + thr - x2)``, acting while ``x2 - x1 < thr``);
* ground ``x0``            -> ``mi.ground(x0)``; port -> ``mi.posInput(0)`` fed by the input.

Timing and initial state (the traps)
------------------------------------
* The forces reach the masses through the ``~`` feedback, i.e. one sample late, and a
  ``mi.mass`` outputs the position it has just computed: Faust output row ``n`` is hapsim
  row ``n + 1`` (the state after ``n + 1`` samples), and the port input at Faust sample ``n``
  is the device position hapsim uses at sample ``n + 1``.
* At Faust sample 0 the masses receive no force (the feedback starts at zero), whereas
  hapsim applies ``F[0]`` computed from ``x[0]``, ``x[-1]``. The first step is made equal by
  folding that force into the mass's delayed position: ``x1_f = x[-1] - T^2 F[0] / m``
  (``x1`` is used by ``mi.mass`` only at its first sample).
* Links' velocity terms are ``(x - x') : initState(r)``: at Faust sample 0 ``x'`` is 0, not
  the previous position, and ``r`` is added. The link sees hapsim's ``x[1]`` there and must
  get ``x[1] - x[0]``, hence ``r = -x[0]`` for each end (``-(x[0] + thr)`` for the first
  mass of a collision, whose position enters as ``x1 + thr``).
* The driver must ``#define FAUSTFLOAT double`` with ``faust -double``, or the outputs are
  rounded to float32.
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
from pathlib import Path
from typing import Sequence

import numpy as np

from hapsim.scene import Scene

#: Faust version whose ``mi.lib`` the mapping was read from.
MIN_VERSION = (2, 54)

__all__ = ["faust_program", "driver_source", "tools_available", "build", "run_binary",
           "bench_binary"]


def _num(v: float) -> str:
    """Faust literal that round-trips the double ``v`` (Faust prints constants in full)."""
    r = repr(float(v))
    if "e" in r or "." in r or "inf" in r or "nan" in r:
        return r
    return r + ".0"


def _initial_forces(scene: Scene) -> np.ndarray:
    """Force on every mass at hapsim sample 0 [N], computed as the engine does."""
    T = scene.period
    x = np.array([m.x0 for m in scene.masses], dtype=float)
    xp = np.array([m.x0 - (m.v0 * T if m.kind == "mass" else 0.0) for m in scene.masses])
    f = np.zeros(len(scene.masses))
    for lk in scene.links:
        a, c = scene.index(lk.m1), scene.index(lk.m2)
        d = x[a] - x[c]
        z = lk.damping / T
        if lk.kind == "contact":
            if not (-d < lk.threshold):
                continue
            force = lk.stiffness * (d + lk.threshold) + z * (d - (xp[a] - xp[c]))
        else:
            force = lk.stiffness * d + z * (d - (xp[a] - xp[c]))
        f[a] -= force
        f[c] += force
    return f


def faust_program(scene: Scene, outputs: Sequence[str] | None = None) -> str:
    """Faust ``mi.lib`` program equivalent to a hapsim scene.

    Parameters
    ----------
    scene : Scene
        A scene whose links all have numeric (K, B); its port (if any) becomes a
        ``mi.posInput`` driven by the program's single audio input, assumed to start from
        the port's scene position 0 [m].
    outputs : sequence of str, optional
        Names of the masses whose positions [m] are the program's outputs, in this order;
        all masses when None.

    Returns
    -------
    str
        Faust source. Output row ``n`` equals hapsim's ``Engine(scene).run`` row ``n + 1``
        (see the module notes for the mapping and the initial-state rules).

    Raises
    ------
    ValueError
        When a link has no numeric (K, B).
    """
    T = scene.period
    names = [m.name for m in scene.masses]
    index = {nm: i for i, nm in enumerate(names)}
    out_idx = list(range(len(names))) if outputs is None else [index[o] for o in outputs]
    f0 = _initial_forces(scene)
    n_m, n_l = len(scene.masses), len(scene.links)
    has_port = any(m.kind == "port" for m in scene.masses)

    # Masses, in scene order; each takes its force (the port also takes the input).
    elems = []
    for i, m in enumerate(scene.masses):
        if m.kind == "mass":
            xp = m.x0 - m.v0 * T
            x1 = xp - T * T * f0[i] / m.mass
            elems.append(f"mi.mass({_num(m.mass / (T * T))}, 0, {_num(m.x0)}, {_num(x1)})")
        elif m.kind == "ground":
            elems.append(f"mi.ground({_num(m.x0)})")
        else:
            elems.append("mi.posInput(0.0)")
    # Links: each takes (x1, x2) and returns (force on m1, force on m2).
    links = []
    for lk in scene.links:
        if np.isnan(lk.stiffness) or np.isnan(lk.damping):
            raise ValueError(f"link {lk.name!r} has no numeric (K, B)")
        a, c = index[lk.m1], index[lk.m2]
        k, z = _num(lk.stiffness), _num(lk.damping / T)
        xa, xc = scene.masses[a].x0, scene.masses[c].x0
        if lk.kind == "contact":
            links.append(f"mi.collision({k}, {z}, {_num(lk.threshold)}, "
                         f"{_num(-(xa + lk.threshold))}, {_num(-xc)})")
        else:
            links.append(f"mi.springDamper({k}, {z}, {_num(-xa)}, {_num(-xc)})")

    fl = [f"f{j}_{e}" for j in range(n_l) for e in (1, 2)]
    mass_in: list[list[str]] = [[] for _ in range(n_m)]
    for j, lk in enumerate(scene.links):
        mass_in[index[lk.m1]].append(f"f{j}_1")
        mass_in[index[lk.m2]].append(f"f{j}_2")
    l2m_args = fl + (["u"] if has_port else [])
    l2m_out = []
    for i, m in enumerate(scene.masses):
        l2m_out.append(" + ".join(mass_in[i]) if mass_in[i] else "0.0")
        if m.kind == "port":
            l2m_out.append("u")
    xs = [f"x{i}" for i in range(n_m)]
    m2l_out = [f"x{index[lk.m1]}, x{index[lk.m2]}" for lk in scene.links]
    m2l_out += [f"x{i}" for i in out_idx]

    lines = ['import("stdfaust.lib");', ""]
    lines.append(f"L2M({', '.join(l2m_args)}) = {', '.join(l2m_out)};")
    lines.append(f"M2L({', '.join(xs)}) = {', '.join(m2l_out)};")
    lines.append("masses = " + ",\n  ".join(elems) + ";")
    links_par = ",\n  ".join(links) if links else "0"
    lines.append(f"links = {links_par};")
    n_out = len(out_idx)
    lines.append(f"model = (L2M : masses : M2L : links, par(i, {n_out}, _)) ~ par(i, {2 * n_l}, _)"
                 f" : par(i, {2 * n_l}, !), par(i, {n_out}, _);")
    lines.append("process = model;")
    return "\n".join(lines) + "\n"


_DRIVER = r"""
// Minimal standalone driver for a Faust-generated class (no architecture files).
#define FAUSTFLOAT double
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <vector>

static double thread_seconds() {
  timespec t;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

struct Meta { void declare(const char*, const char*) {} };
struct Soundfile;
struct UI {
  void openTabBox(const char*) {} void openHorizontalBox(const char*) {}
  void openVerticalBox(const char*) {} void closeBox() {}
  void declare(FAUSTFLOAT*, const char*, const char*) {}
  void addButton(const char*, FAUSTFLOAT*) {} void addCheckButton(const char*, FAUSTFLOAT*) {}
  void addVerticalSlider(const char*, FAUSTFLOAT*, FAUSTFLOAT, FAUSTFLOAT, FAUSTFLOAT, FAUSTFLOAT) {}
  void addHorizontalSlider(const char*, FAUSTFLOAT*, FAUSTFLOAT, FAUSTFLOAT, FAUSTFLOAT, FAUSTFLOAT) {}
  void addNumEntry(const char*, FAUSTFLOAT*, FAUSTFLOAT, FAUSTFLOAT, FAUSTFLOAT, FAUSTFLOAT) {}
  void addHorizontalBargraph(const char*, FAUSTFLOAT*, FAUSTFLOAT, FAUSTFLOAT) {}
  void addVerticalBargraph(const char*, FAUSTFLOAT*, FAUSTFLOAT, FAUSTFLOAT) {}
  void addSoundfile(const char*, const char*, Soundfile**) {}
};
struct dsp {
  virtual ~dsp() {}
};

#include "model.h"

// usage: prog run N   (reads N input samples from stdin if the model has an input,
//                      prints N rows of outputs, %.17g)
//        prog bench N REPEATS BLOCK   (prints the median thread CPU seconds per N samples)
int main(int argc, char** argv) {
  if (argc < 3) return 2;
  long n = atol(argv[2]);
  mydsp d;
  d.init(44100);
  int ni = d.getNumInputs(), no = d.getNumOutputs();
  if (!strcmp(argv[1], "run")) {
    std::vector<std::vector<double>> in(ni, std::vector<double>(n, 0.0));
    std::vector<std::vector<double>> out(no, std::vector<double>(n, 0.0));
    for (long s = 0; s < n; ++s)
      for (int c = 0; c < ni; ++c)
        if (scanf("%lf", &in[c][s]) != 1) return 3;
    std::vector<double*> ip(ni), op(no);
    for (int c = 0; c < ni; ++c) ip[c] = in[c].data();
    for (int c = 0; c < no; ++c) op[c] = out[c].data();
    d.compute((int)n, ip.data(), op.data());
    for (long s = 0; s < n; ++s) {
      for (int c = 0; c < no; ++c) printf(c ? " %.17g" : "%.17g", out[c][s]);
      printf("\n");
    }
    return 0;
  }
  int reps = argc > 3 ? atoi(argv[3]) : 5;
  int block = argc > 4 ? atoi(argv[4]) : 64;
  std::vector<std::vector<double>> in(ni, std::vector<double>(block, 0.0));
  std::vector<std::vector<double>> out(no, std::vector<double>(block, 0.0));
  std::vector<double*> ip(ni), op(no);
  for (int c = 0; c < ni; ++c) ip[c] = in[c].data();
  for (int c = 0; c < no; ++c) op[c] = out[c].data();
  std::vector<double> times;
  double sink = 0.0;
  for (int r = 0; r < reps; ++r) {
    double t0 = thread_seconds();
    for (long s = 0; s < n; s += block) {
      d.compute(block, ip.data(), op.data());
      sink += op.empty() ? 0.0 : op[0][0];
    }
    times.push_back(thread_seconds() - t0);
  }
  std::sort(times.begin(), times.end());
  printf("%.9g %ld %g\n", times[times.size() / 2], ((n + block - 1) / block) * (long)block, sink);
  return 0;
}
"""


def driver_source() -> str:
    """C++ driver (``main``) for the Faust class ``mydsp`` included from ``model.h``.

    Returns
    -------
    str
        C++ source: ``prog run N`` reads ``N`` input samples per input channel from stdin
        and prints ``N`` rows of outputs (``%.17g``); ``prog bench N REPEATS BLOCK`` prints
        the median thread CPU time [s] of ``N`` samples over ``REPEATS`` runs, the samples actually run
        and a checksum.
    """
    return _DRIVER


def tools_available() -> str | None:
    """Why the Faust oracle cannot run here, or None when ``faust`` and ``c++`` exist.

    Returns
    -------
    str or None
        A human-readable reason to skip (no ``faust``, no compiler, or a Faust older than
        :data:`MIN_VERSION`), or None.
    """
    if shutil.which("faust") is None:
        return "faust is not on PATH (apt-get install faust)"
    if shutil.which(os.environ.get("CXX", "c++")) is None and shutil.which("g++") is None:
        return "no C++ compiler (c++/g++) on PATH"
    try:
        out = subprocess.run(["faust", "--version"], capture_output=True, text=True,
                             timeout=30).stdout
        ver = tuple(int(p) for p in out.split("Version")[1].split()[0].split(".")[:2])
    except (OSError, subprocess.SubprocessError, IndexError, ValueError):
        return "could not read `faust --version`"
    if ver < MIN_VERSION:
        return (f"faust {ver[0]}.{ver[1]} is older than {MIN_VERSION[0]}.{MIN_VERSION[1]}, "
                "whose mi.lib (collision, initState) the mapping was derived from")
    return None


def _cxx() -> str:
    cxx = os.environ.get("CXX", "c++")
    return cxx if shutil.which(cxx) else "g++"


def _limit(mem_bytes: int | None):
    if mem_bytes is None:
        return None

    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (mem_bytes, mem_bytes))
    return preexec


def build(program: str, workdir: str | os.PathLike, opt: str = "-O1",
          mem_bytes: int | None = None, timeout: float | None = None) -> Path:
    """Compile a Faust program and the driver into an executable.

    Parameters
    ----------
    program : str
        Faust source (from :func:`faust_program`).
    workdir : path
        Existing scratch directory (a temporary one: files are written there).
    opt : str
        C++ optimisation flag, e.g. ``"-O1"`` (tests) or ``"-O3"`` (benchmarks).
    mem_bytes : int, optional
        Address-space limit [bytes] applied to ``faust`` and the compiler.
    timeout : float, optional
        Wall-clock limit [s] for each of the two compilation steps.

    Returns
    -------
    Path
        The executable.

    Raises
    ------
    subprocess.CalledProcessError
        When ``faust`` or the compiler fails (stderr attached).
    subprocess.TimeoutExpired
        When a step exceeds ``timeout``.
    """
    wd = Path(workdir)
    (wd / "model.dsp").write_text(program)
    (wd / "driver.cpp").write_text(driver_source())
    pre = _limit(mem_bytes)
    subprocess.run(["faust", "-double", "-lang", "cpp", "-t", "0", "-cn", "mydsp",
                    "model.dsp", "-o", "model.h"], cwd=wd, check=True, capture_output=True,
                   text=True, preexec_fn=pre, timeout=timeout)
    exe = wd / "model"
    subprocess.run([_cxx(), opt, "-std=c++11", "driver.cpp", "-o", str(exe)], cwd=wd,
                   check=True, capture_output=True, text=True, preexec_fn=pre, timeout=timeout)
    return exe


def run_binary(exe: str | os.PathLike, n: int, inputs: np.ndarray | None = None) -> np.ndarray:
    """Run a built program for ``n`` samples and return its outputs.

    Parameters
    ----------
    exe : path
        Executable from :func:`build`.
    n : int
        Samples.
    inputs : ndarray, shape (n,), optional
        The input signal (port position [m]) when the program has one.

    Returns
    -------
    ndarray, shape (n, n_outputs)
        Outputs per sample [m].
    """
    stdin = "" if inputs is None else "\n".join(repr(float(v)) for v in inputs) + "\n"
    res = subprocess.run([str(exe), "run", str(n)], input=stdin, capture_output=True,
                         text=True, check=True)
    return np.loadtxt(res.stdout.splitlines(), ndmin=2)


def bench_binary(exe: str | os.PathLike, n: int, repeats: int = 5, block: int = 64) -> float:
    """Median thread CPU time of ``n`` samples of a built program [s].

    Parameters
    ----------
    exe : path
        Executable from :func:`build`.
    n : int
        Samples per repeat (rounded up to whole blocks; the time is rescaled to ``n``).
    repeats : int
        Repeats; the median is returned.
    block : int
        Samples per ``compute`` call (an audio buffer).

    Returns
    -------
    float
        Median seconds for ``n`` samples.
    """
    res = subprocess.run([str(exe), "bench", str(n), str(repeats), str(block)],
                         capture_output=True, text=True, check=True)
    med, ran, _ = res.stdout.split()
    return float(med) * n / int(ran)
