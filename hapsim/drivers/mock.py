"""Mocks of the driver protocols' devices, byte for byte, on a pseudo-terminal.

The physics is the mock device's (:class:`hapsim.daemon.mock.MockPhysics`: exact ZOH,
optional Coulomb friction, noise); the bytes are the device's protocol. The device answers
each host packet: it applies the force of the packet ``d`` packets back (the scene's
``device.delay``; zero before that), advances one period, and replies with one record of
the new position -- so the host's clock paces it (the protocols are host-clocked). A
packet that does not decode is dropped (the force last applied is held); a silence of more
than ``watchdog`` seconds zeroes the force.
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import sys
import time
from collections import deque

from hapsim.device_model import MockPhysics

__all__ = ["FireFaderDevice", "HaplyDevice", "HapkitSerialDevice", "serve", "EmbeddedDriverMock", "main"]


class _Actuated:
    """The physics side shared by the driver mocks: delay queue, clamp, one period per
    command.

    Parameters
    ----------
    device : hapsim.scene.Device
        Mass (or inertia), friction, delay and imperfections of the driven axis.
    rate_hz : float
        Period the host runs at [Hz] (one period per command).
    excitation : hapsim.scene.Excitation, optional
        Initial displacement / velocity / hand force.
    limit : float
        The device's own force clamp [N] (or [N m]); the device section's is also applied.
    seed : int
        Sensor-noise seed.

    Attributes
    ----------
    applied : list of float
        Forces applied per command (for tests).
    """

    def __init__(self, device, rate_hz, excitation, limit, seed):
        self.physics = MockPhysics(device, rate_hz, excitation, seed=seed)
        self.delay = int(device.delay)
        self.limit = min(float(device.force_limit), float(limit))
        self._fifo: deque = deque([0.0] * self.delay)
        self.applied: list = []
        self.held = 0.0
        self.clamped = 0
        self.last_command = 0.0

    def apply(self, force: float) -> None:
        """Queue ``force``, apply the one due (``delay`` commands back), advance a period."""
        self.last_command = force
        if not math.isfinite(force):
            force = 0.0                     # a corrupted float is no reason to push hard
        self._fifo.append(force)
        due = self._fifo.popleft()
        if abs(due) > self.limit:
            due = math.copysign(self.limit, due)
            self.clamped += 1
        self.held = due
        self.applied.append(due)
        self.physics.advance(due)

    def commands(self) -> int:
        """Force commands applied so far."""
        return len(self.applied)

    def watchdog(self) -> None:
        """No command for too long: zero the force from now on (the queue too)."""
        self._fifo = deque([0.0] * self.delay)
        self.held = 0.0


class FireFaderDevice(_Actuated):
    """A FireFader whose fader A is the mock device's moving mass.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`_Actuated`.
    full_scale : float
        Force at 127 counts [N].

    Attributes
    ----------
    decoder : PacketDecoder
        Its counters are the device's view of bad bytes.
    """

    def __init__(self, device, rate_hz: float, excitation=None, *, full_scale: float = 1.56,
                 seed: int = 0) -> None:
        from hapsim.drivers import firefader as ff
        self._ff = ff
        self.full_scale = float(full_scale)
        super().__init__(device, rate_hz, excitation, 126 * full_scale / 127, seed)
        self.decoder = ff.PacketDecoder()

    def position_count(self) -> int:
        """Fader A's reading: the sampled position in counts from the centre, 0..254."""
        ff = self._ff
        c = ff.CENTRE + round(self.physics.sample() / ff.METRES_PER_COUNT)
        return int(min(max(c, 0), ff.POSITION_MAX))

    def step(self, count_a: int) -> bytes:
        """One packet: apply the force due, advance a period, answer with a record."""
        self.apply(count_a * self.full_scale / 127.0)
        return self._ff.encode_record(self.position_count(), self._ff.CENTRE)

    def feed(self, data: bytes) -> bytes:
        """Bytes from the host in, the records to send back out."""
        out = b""
        for a, _b in self.decoder.feed(data):
            out += self.step(a)
        return out


class HaplyDevice(_Actuated):
    """A Haply M3 board whose motor 1 / encoder 1 joint is the mock device's axis
    (rotary: mass = inertia [kg m^2], force = torque [N m], position = angle [rad]).

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`_Actuated`.
    resolution : float
        Encoder counts per revolution (the set-up's value replaces it).

    Attributes
    ----------
    decoder : CommandDecoder
    """

    def __init__(self, device, rate_hz: float, excitation=None, *, resolution: float = 4880.0,
                 seed: int = 0) -> None:
        from hapsim.drivers import haply as hp
        self._hp = hp
        super().__init__(device, rate_hz, excitation, hp.MAX_TORQUE, seed)
        self.decoder = hp.CommandDecoder()
        self.resolution = float(resolution)

    def angle_deg(self) -> float:
        """Encoder 1's reading [deg]: 360 counts / resolution (firmware ``read_encoder_value``)."""
        counts = round(self.physics.sample() / (2 * math.pi) * self.resolution)
        return 360.0 * counts / self.resolution

    def feed(self, data: bytes) -> bytes:
        """Bytes from the host in, the replies out (one per write)."""
        out = b""
        for cmd in self.decoder.feed(data):
            if cmd[0] == "setup" and self.decoder.resolution:
                self.resolution = self.decoder.resolution
            if cmd[0] != "write":
                continue
            _, wid, tq = cmd
            if wid != self.decoder.id or not tq:
                out += bytes([wid])          # the firmware answers [id] and no values
                continue
            self.apply(tq[0])
            out += self._hp.reply_packet(wid, self.angle_deg())
        return out


class HapkitSerialDevice(_Actuated):
    """A Hapkit running the WHC2017 sketch with the host-force function: its handle is the
    mock device's moving mass.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`_Actuated`.
    force_limit : float
        The firmware's force clamp [N].

    Attributes
    ----------
    decoder : CommandDecoder
    """

    def __init__(self, device, rate_hz: float, excitation=None, *, force_limit: float = 2.0,
                 seed: int = 0) -> None:
        from hapsim.drivers import hapkit_serial as hk
        self._hk = hk
        super().__init__(device, rate_hz, excitation, force_limit, seed)
        self.decoder = hk.CommandDecoder()

    def feed(self, data: bytes) -> bytes:
        """Bytes from the host in, one 9-byte reply per command out."""
        out = b""
        for f in self.decoder.feed(data):
            self.apply(f)
            out += self._hk.reply_packet(self.decoder.function, self.physics.sample(),
                                         self.held)
        return out


def serve(fd: int, dev, *, watchdog: float = 0.5, stop=None) -> dict:
    """Serve ``dev`` on a byte stream until EOF (host closed) or ``stop()`` is true.

    Parameters
    ----------
    fd : int
        Master side of the pty.
    dev : FireFaderDevice or HaplyDevice
        The device (``feed(bytes) -> bytes``, ``decoder.stats``, ``watchdog()``).
    watchdog : float
        Silence after which the force is zeroed [s] (like the FireFader host's serial
        timeout). The mock is paced by the host's commands, so this only guards against a
        host that went away; 0.5 s by default, longer than a loaded host ever stalls.
    stop : callable, optional
        Polled; serving ends when it returns True.

    Returns
    -------
    dict
        ``packets``, ``decoder`` counters, ``watchdog_trips``, ``watchdog_at`` (packets
        received before each trip: the queue of forces was zeroed before the next), and
        the keys of
        :class:`hapsim.daemon.mock.MockStats` the run report prints (``ticks`` = packets,
        ``late`` and ``overruns`` 0: the device is paced by the packets; ``clamped``;
        ``last_applied`` [N]; ``saw_stop``: the last packet commanded zero force, which
        is all a STOP is in this protocol).
    """
    os.set_blocking(fd, False)
    trips = 0
    trip_at: list = []
    last = time.monotonic()
    tripped = False
    while not (stop and stop()):
        r, _, _ = select.select([fd], [], [], 0.02)
        if not r:
            if not tripped and time.monotonic() - last > watchdog:
                dev.watchdog()
                trips += 1
                trip_at.append(dev.commands())
                tripped = True
            continue
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            continue
        except OSError:
            break
        if not data:
            break
        last = time.monotonic()
        tripped = False
        out = dev.feed(data)
        if out:
            try:
                os.write(fd, out)
            except OSError:
                break
    n = dev.commands()
    return {"packets": n, "decoder": dict(dev.decoder.stats), "watchdog_trips": trips,
            "watchdog_at": trip_at,
            "ticks": n, "late": 0, "overruns": 0, "clamped": dev.clamped,
            "last_applied": dev.held, "saw_stop": bool(n and dev.last_command == 0)}


def main(argv=None) -> int:
    """Child-process entry: ``python -m hapsim.drivers.mock --fd N --spec JSON --rate R``."""
    import argparse
    import dataclasses

    from hapsim.scene import Device, Excitation
    p = argparse.ArgumentParser(prog="hapsim.drivers.mock")
    p.add_argument("--fd", type=int, required=True)
    p.add_argument("--spec", required=True)
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--report")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    spec = json.loads(a.spec)
    d = spec["device"]
    if d.get("force_limit") is None:
        d["force_limit"] = math.inf
    device = Device(**d)
    exc = spec["excitation"]
    fields = {f.name for f in dataclasses.fields(Excitation)}
    if exc.get("impulse"):
        from hapsim.scene import Impulse
        exc["impulse"] = Impulse(**exc["impulse"])
    excitation = Excitation(**{k: v for k, v in exc.items() if k in fields})
    if spec.get("driver", "firefader") == "haply":
        dev = HaplyDevice(device, a.rate, excitation, seed=a.seed)
    elif spec.get("driver") == "hapkit-serial":
        dev = HapkitSerialDevice(device, a.rate, excitation, seed=a.seed)
    else:
        dev = FireFaderDevice(device, a.rate, excitation, seed=a.seed,
                              full_scale=float(spec.get("full_scale", 1.56)))
    flag = {"stop": False}
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: flag.__setitem__("stop", True))
    rep = serve(a.fd, dev, stop=lambda: flag["stop"])
    if a.report:
        with open(a.report + ".partial", "w") as fh:
            json.dump(rep, fh)
        os.replace(a.report + ".partial", a.report)
    return 0


class EmbeddedDriverMock:
    """A driver mock in a child process on the master side of a new pty.

    Parameters
    ----------
    driver : str
        Driver name (``"firefader"``).
    device, excitation
        What the mock models (:class:`hapsim.scene.Device`, :class:`~hapsim.scene.Excitation`).
    rate_hz : float
        Host rate [Hz] (one period per packet).
    seed : int
        Sensor-noise seed.
    full_scale : float
        FireFader force at 127 counts [N].

    Attributes
    ----------
    port : str
        The slave path to open.
    """

    def __init__(self, driver: str, device, excitation, rate_hz: float, *, seed: int = 0,
                 full_scale: float = 1.56) -> None:
        import dataclasses
        import pty
        import subprocess
        import tempfile
        import tty

        from hapsim.errors import ConfigError
        from hapsim.spawn import child_env
        if driver not in ("firefader", "haply", "hapkit-serial"):
            raise ConfigError(f"no mock for driver {driver!r}; valid: firefader, haply, "
                              "hapkit-serial",
                              key="--driver")
        master, slave = pty.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        self._slave = slave
        fd, self.report_path = tempfile.mkstemp(prefix="hapsim-drvmock-", suffix=".json")
        os.close(fd)
        os.unlink(self.report_path)
        spec = {"device": dataclasses.asdict(device), "excitation": dataclasses.asdict(excitation),
                "full_scale": full_scale, "driver": driver}
        if not math.isfinite(spec["device"]["force_limit"]):
            spec["device"]["force_limit"] = None
        env = child_env()
        cmd = [sys.executable, "-m", "hapsim.drivers.mock", "--fd", str(master), "--spec",
               json.dumps(spec), "--rate", repr(float(rate_hz)), "--report", self.report_path,
               "--seed", str(seed)]
        try:
            self.proc = subprocess.Popen(cmd, pass_fds=(master,), env=env,
                                         stdin=subprocess.DEVNULL, start_new_session=True)
        finally:
            os.close(master)

    def release_slave(self) -> None:
        """Close this object's copy of the slave (after the host opened the port)."""
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None

    def report(self, timeout: float = 3.0):
        """Wait for the child to end (the host closed the port) and return its report."""
        try:
            self.proc.wait(timeout)
        except Exception:
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except Exception:
                self.proc.kill()
        try:
            with open(self.report_path) as fh:
                return json.load(fh)
        except (OSError, ValueError):
            return None

    def close(self) -> None:
        """End the child and release the pty (idempotent)."""
        self.release_slave()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(2.0)
            except Exception:
                self.proc.kill()
        try:
            os.unlink(self.report_path)
        except OSError:
            pass


if __name__ == "__main__":
    sys.exit(main())
