"""The emulated Hapkit 3 board: build the firmware and the simavr board program, start it.

The reference firmware (``firmware_protocol/firmware/hapkit``, C99 + avr-libc, built with
avr-gcc) runs cycle by cycle on simavr's ATmega328P inside ``hapkit_board``
(``firmware_protocol/firmware/sim``, C on libsimavr), which wires the device's physics to
the chip's pins and bridges its UART to a pseudo-terminal. Both are built with ``make``
when missing or older than their sources.
"""

from __future__ import annotations

import fcntl
import filecmp
import hashlib
import importlib.util
import math
import os
import shutil
import subprocess
from pathlib import Path

from hapsim.errors import DeviceError

def _build_tree(package: Path, cache: Path) -> Path:
    """Where the firmware is built: the installed ``firmware_protocol`` package itself when
    it is writable (a checkout, an editable or a root install), else a per-user copy.

    Parameters
    ----------
    package : pathlib.Path
        The ``firmware_protocol`` package directory (it holds ``c/`` and ``firmware/``, the
        sources shipped as package data).
    cache : pathlib.Path
        The user's cache directory (``$XDG_CACHE_HOME`` or ``~/.cache``).

    Returns
    -------
    pathlib.Path
        A directory holding (or about to hold, see :func:`make`) ``c/`` and ``firmware/``.
    """
    if os.access(package / "firmware", os.W_OK):
        return package
    tag = hashlib.sha1(str(package).encode()).hexdigest()[:12]   # one copy per installation
    return cache / "hapsim" / f"firmware_protocol-{tag}"


#: The ``firmware_protocol`` package as installed (its firmware sources are package data).
PACKAGE = Path(importlib.util.find_spec("firmware_protocol").origin).resolve().parent
#: The tree ``make`` runs in: the package itself, or a writable copy of its sources.
BUILD_TREE = _build_tree(PACKAGE, Path(os.environ.get("XDG_CACHE_HOME")
                                        or Path.home() / ".cache"))
ROOT = BUILD_TREE / "firmware"
FIRMWARE_DIR = ROOT / "hapkit"
BOARD_DIR = ROOT / "sim"
FIRMWARE_ELF = FIRMWARE_DIR / "hapkit.elf"
VECTORS_ELF = FIRMWARE_DIR / "hapkit_vectors.elf"
BOARD = BOARD_DIR / "hapkit_board"
#: Held (``flock``) while ``make`` runs, so that two processes building at once (the test
#: suite's two workers, two ``hapsim mock --board``) never write the same ELF together.
BUILD_LOCK = ROOT / ".build.lock"


def missing_tools() -> str | None:
    """What is missing to build and run the emulated board, or None.

    Returns
    -------
    str or None
        A sentence naming the missing programs/headers (the Debian packages gcc-avr,
        avr-libc, simavr, libsimavr-dev provide them), or None when all are present.
    """
    missing = [t for t in ("make", "cc", "avr-gcc") if shutil.which(t) is None]
    if not Path("/usr/include/simavr/sim_avr.h").exists() and not os.environ.get(
            "SIMAVR_INCLUDE"):
        missing.append("simavr headers (libsimavr-dev)")
    if not any(Path(d, "avr", "io.h").exists() for d in ("/usr/lib/avr/include",
                                                          "/usr/avr/include")):
        missing.append("avr-libc")
    if missing:
        return ("not installed: " + ", ".join(missing) +
                " (Debian packages gcc-avr, avr-libc, simavr, libsimavr-dev)")
    return None


def build(*, quiet: bool = True) -> dict:
    """Build the firmware (``hapkit.elf``, ``hapkit_vectors.elf``) and ``hapkit_board``.

    ``make`` rebuilds only what is missing or older than its sources; warnings are errors
    (``-Wall -Wextra -Werror``). Concurrent builders are serialised by an exclusive
    ``flock`` on :data:`BUILD_LOCK`. The UART runs at the Makefile's ``BAUD`` (2 Mbaud).

    Parameters
    ----------
    quiet : bool
        Capture make's output (it is in the error on failure) instead of printing it.

    Returns
    -------
    dict
        ``board``, ``elf``, ``vectors_elf`` (paths as str), ``output`` (make's output:
        compiler lines and the ``avr-size`` table of flash and RAM use).

    Raises
    ------
    DeviceError
        A tool is missing (:func:`missing_tools`) or make failed (its output attached).
    """
    output = make("the emulated Hapkit board",
                  ((FIRMWARE_DIR, "all"), (BOARD_DIR, "hapkit_board")), quiet=quiet)
    return {"board": str(BOARD), "elf": str(FIRMWARE_ELF), "vectors_elf": str(VECTORS_ELF),
            "output": output}


def make(what: str, steps, *, quiet: bool = True) -> str:
    """Run ``make -C DIR TARGET`` for each step, under the firmware tree's build lock
    (one builder at a time: the second waits, then finds everything up to date).

    Parameters
    ----------
    what : str
        What is built, for the error (``"the emulated Hapkit board"``).
    steps : iterable of (path-like, str)
        ``(directory, target)`` in order.
    quiet : bool
        Capture make's output instead of printing it.

    Returns
    -------
    str
        make's output, every step's.

    Raises
    ------
    DeviceError
        A tool is missing (:func:`missing_tools`) or a make failed (its output attached).
    """
    why = missing_tools()
    if why:
        raise DeviceError(f"cannot build {what}: {why}")
    out = []
    ROOT.mkdir(parents=True, exist_ok=True)
    with open(BUILD_LOCK, "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        _copy_sources()
        for d, target in steps:
            r = subprocess.run(["make", "-C", str(d), target], capture_output=True, text=True)
            out.append(r.stdout + r.stderr)
            if r.returncode != 0:
                raise DeviceError(f"make in {d} failed (exit {r.returncode}):\n{out[-1]}")
            if not quiet:
                print(out[-1], end="", flush=True)
    return "".join(out)


def _copy_sources() -> None:
    """Bring the build tree's sources up to date with the installed package's (a no-op when
    the package itself is the build tree): a changed file is copied, so ``make`` sees it
    newer than what was built from the old one."""
    if BUILD_TREE == PACKAGE:
        return
    for src in PACKAGE.rglob("*"):
        rel = src.relative_to(PACKAGE)
        if not src.is_file() or rel.parts[0] not in ("c", "firmware"):
            continue
        dst = BUILD_TREE / rel
        if not dst.exists() or not filecmp.cmp(src, dst, shallow=False):
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)


def shipped_scene(name: str) -> str:
    """A scene of the checkout's ``configs/`` (the default device of ``hapsim mock
    --firmware`` and ``hapsim zwidth --firmware``).

    Parameters
    ----------
    name : str
        File name in ``configs/`` (``"hapkit.yaml"``).

    Returns
    -------
    str
        Its path.

    Raises
    ------
    hapsim.errors.ConfigError
        The package was installed without the source checkout, so there is no ``configs/``:
        the message asks for ``--scene``.
    """
    from hapsim.errors import ConfigError
    path = Path(__file__).resolve().parents[2] / "configs" / name
    if not path.is_file():
        raise ConfigError(f"no default scene here (configs/{name} comes with the source "
                          "checkout): give the device's scene with --scene", key="--scene")
    return str(path)


def board_command(device, excitation, *, elf: str | None = None, realtime: bool | None = None,
                  report: str | None = None, link: str | None = None,
                  wait_ms: float | None = None, duration: float | None = None,
                  trace: str | None = None, spin_us: float | None = None,
                  lockstep: bool = False) -> list[str]:
    """The ``hapkit_board`` command line for a scene's device and excitation.

    Parameters
    ----------
    device : hapsim.scene.Device
        ``mass`` [kg], ``friction`` b0 [N s/m] and ``coulomb`` [N] become the handle's
        physics (``delay``, ``hold`` and ``force_limit`` are the firmware's own).
    excitation : hapsim.scene.Excitation
        ``x0`` [m] and ``v0`` [m/s]: where the hand lets go of the handle at each CONFIG
        (it brings it back there at STOP, without a jump); an
        ``impulse`` (force [N], start [s], duration [s]) becomes the hand's push.
    elf : str, optional
        Firmware ELF (default: the built ``hapkit.elf``).
    realtime : bool, optional
        Lock the emulated clock to the wall clock (the board keeps its own time); default
        ``not lockstep``.
    report, link : str, optional
        JSON report file written on exit; symbolic link kept to the pty.
    wait_ms, duration : float, optional
        Longest wait for the host per STATE [ms] (default: as long as the host keeps the
        port open, so no FORCE is late however slow the host); emulated time to run [s].
    trace : str, optional
        File the board writes its event trace to on exit (every tick, conversion, PWM
        change, STATE, FORCE read and fed, wait for the wall clock; emulated cycle and
        CLOCK_MONOTONIC; read by ``tools/bench_firmware.py``).
    spin_us : float, optional
        Real time: the longest spin per tick [us] while the board waits for the host's FORCE
        (emulating in 10 us steps, never ahead of the wall clock); default 0, no spin.
    lockstep : bool
        The board as fast as the host answers (each STATE waits for its FORCE), asked for
        by name (deterministic tests); default False: the wall clock.

    Returns
    -------
    list of str
        argv of the board program.
    """
    cmd = [str(BOARD), elf or str(FIRMWARE_ELF),
           "--mass", repr(float(device.mass)), "--friction", repr(float(device.friction)),
           "--coulomb", repr(float(getattr(device, "coulomb", 0.0) or 0.0)),
           "--x0", repr(float(excitation.x0 or 0.0)),
           "--v0", repr(float(excitation.v0 or 0.0))]
    imp = getattr(excitation, "impulse", None)
    if imp is not None:
        cmd += ["--hand-force", repr(float(imp.force)), "--hand-start", repr(float(imp.start)),
                "--hand-duration", repr(float(imp.duration))]
    if realtime is None:
        realtime = not lockstep
    if realtime:
        cmd.append("--realtime")
    if report:
        cmd += ["--report", report]
    if link:
        cmd += ["--link", link]
    if wait_ms is not None:
        cmd += ["--wait-ms", repr(float(wait_ms))]
    if duration is not None and math.isfinite(duration):
        cmd += ["--duration", repr(float(duration))]
    if trace:
        cmd += ["--trace", trace]
    if spin_us:
        cmd += ["--spin-us", repr(float(spin_us))]
    return cmd

